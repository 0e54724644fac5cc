//! Typed ports: a publisher paired with the notifier of its event service ([`Output`]), and a
//! subscriber paired with a listener the process's WaitSet blocks on ([`Input`]).
//!
//! Every port is created with the QoS of its [`ServiceSpec`](shared_types::services::ServiceSpec),
//! set explicitly. [`Output::send`] stamps `seq` and `publish_ns` (and `origin_ns` when the caller
//! left it 0, i.e. for sensor sources), sends and notifies. [`Input`] receives and records hop and
//! end-to-end latency into the port's histograms before handing the sample to the caller.

use std::any::Any;
use std::cell::RefCell;
use std::collections::{HashMap, VecDeque};
use std::fmt::Debug;
use std::mem::MaybeUninit;
use std::ops::Deref;
use std::rc::Rc;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;
use iceoryx2::sample_mut::SampleMut;
use iceoryx2::sample_mut_uninit::SampleMutUninit;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory;
use shared_types::HasMsgHeader;
use shared_types::services::Qos;

use crate::clock::monotonic_ns;
use crate::stats::PortStats;

mod samples;
pub use samples::*;

/// A user header: any wire header that starts with the common `MsgHeader`.
pub trait Header: Debug + ZeroCopySend + Default + HasMsgHeader + 'static {}
impl<T: Debug + ZeroCopySend + Default + HasMsgHeader + 'static> Header for T {}

/// Errors of creating or using a port. Each names the service.
#[derive(Debug, thiserror::Error)]
pub enum PortError {
    /// The service name is not valid.
    #[error("invalid service name `{0}`")]
    InvalidName(String),
    /// The publish-subscribe service could not be opened or created (often: another process
    /// created it with a different payload type, size or QoS).
    #[error("cannot open service `{service}`: {reason}")]
    Open {
        /// Service.
        service: String,
        /// iceoryx2's reason.
        reason: String,
    },
    /// The port could not be created (e.g. too many publishers/subscribers).
    #[error("cannot create a port on `{service}`: {reason}")]
    Create {
        /// Service.
        service: String,
        /// iceoryx2's reason.
        reason: String,
    },
    /// Loaning, sending, receiving or notifying failed.
    #[error("`{service}`: {op} failed: {reason}")]
    Io {
        /// Service.
        service: String,
        /// The operation.
        op: &'static str,
        /// iceoryx2's reason.
        reason: String,
    },
}

fn io_err(service: &str, op: &'static str, e: impl Debug) -> PortError {
    PortError::Io { service: service.to_string(), op, reason: format!("{e:?}") }
}

fn service_name(name: &str) -> Result<ServiceName, PortError> {
    ServiceName::new(name).map_err(|_| PortError::InvalidName(name.to_string()))
}

/// A payload type a port can carry: a fixed-size wire type `T` or a slice `[T]`.
pub trait Payload: Debug + IceoryxSend + 'static {
    /// Opens (or creates) the publish-subscribe service `name` with this payload, user header `H`
    /// and `qos`.
    fn open_service<H: Header>(
        node: &Node<ipc::Service>,
        name: &str,
        qos: &Qos,
    ) -> Result<PortFactory<ipc::Service, Self, H>, PortError>;

    /// Receives from an iceoryx2 subscriber of this payload.
    fn receive_shm<H: Header>(
        subscriber: &Subscriber<ipc::Service, Self, H>,
        service: &str,
    ) -> Result<Option<Sample<ipc::Service, Self, H>>, PortError>;

    /// The payload of a received sample.
    fn sample_payload<H: Header>(sample: &Sample<ipc::Service, Self, H>) -> &Self;

    /// The payload of a loaned sample.
    fn loaned_payload<H: Header>(sample: &SampleMut<ipc::Service, Self, H>) -> &Self;

    /// The payload of a loaned sample, to write.
    fn loaned_payload_mut<H: Header>(sample: &mut SampleMut<ipc::Service, Self, H>) -> &mut Self;
}

macro_rules! open_with_qos {
    ($builder:expr, $name:expr, $qos:expr) => {{
        // The runtime has added the run's `run.extra_subscribers` (Qos::with_extra).
        let qos = $qos;
        $builder
            .max_publishers(qos.max_publishers)
            .max_subscribers(qos.max_subscribers)
            .max_nodes(qos.max_nodes)
            .subscriber_max_buffer_size(qos.subscriber_buffer)
            .subscriber_max_borrowed_samples(qos.subscriber_borrowed)
            .history_size(qos.history)
            .enable_safe_overflow(qos.safe_overflow)
            .open_or_create()
            .map_err(|e| PortError::Open { service: $name.to_string(), reason: format!("{e:?}") })
    }};
}

macro_rules! with_delivery {
    ($builder:expr, $delivery:expr, $bp:expr) => {{
        let bp = $bp.clone();
        match $delivery {
            Delivery::DiscardWhenFull => $builder
                .backpressure_strategy(BackpressureStrategy::DiscardData)
                .set_backpressure_handler(move |info: &iceoryx2::port::BackpressureInfo| {
                    bp.dropped_for(info.receiver_port_id);
                    iceoryx2::port::BackpressureAction::DiscardData
                }),
            Delivery::WaitWhenFull { max_wait } => $builder
                .backpressure_strategy(BackpressureStrategy::RetryUntilDelivered)
                .set_backpressure_handler(move |info: &iceoryx2::port::BackpressureInfo| bp.wait(info, max_wait)),
        }
    }};
}

impl<T: Debug + ZeroCopySend + 'static> Payload for T {
    fn open_service<H: Header>(
        node: &Node<ipc::Service>,
        name: &str,
        qos: &Qos,
    ) -> Result<PortFactory<ipc::Service, Self, H>, PortError> {
        open_with_qos!(
            node.service_builder(&service_name(name)?).publish_subscribe::<T>().user_header::<H>(),
            name,
            qos
        )
    }

    fn receive_shm<H: Header>(
        subscriber: &Subscriber<ipc::Service, Self, H>,
        service: &str,
    ) -> Result<Option<Sample<ipc::Service, Self, H>>, PortError> {
        subscriber.receive().map_err(|e| io_err(service, "receive", e))
    }

    fn sample_payload<H: Header>(sample: &Sample<ipc::Service, Self, H>) -> &Self {
        sample.payload()
    }

    fn loaned_payload<H: Header>(sample: &SampleMut<ipc::Service, Self, H>) -> &Self {
        sample.payload()
    }

    fn loaned_payload_mut<H: Header>(sample: &mut SampleMut<ipc::Service, Self, H>) -> &mut Self {
        sample.payload_mut()
    }
}

impl<T: Debug + ZeroCopySend + 'static> Payload for [T] {
    fn open_service<H: Header>(
        node: &Node<ipc::Service>,
        name: &str,
        qos: &Qos,
    ) -> Result<PortFactory<ipc::Service, Self, H>, PortError> {
        open_with_qos!(
            node.service_builder(&service_name(name)?).publish_subscribe::<[T]>().user_header::<H>(),
            name,
            qos
        )
    }

    fn receive_shm<H: Header>(
        subscriber: &Subscriber<ipc::Service, Self, H>,
        service: &str,
    ) -> Result<Option<Sample<ipc::Service, Self, H>>, PortError> {
        subscriber.receive().map_err(|e| io_err(service, "receive", e))
    }

    fn sample_payload<H: Header>(sample: &Sample<ipc::Service, Self, H>) -> &Self {
        sample.payload()
    }

    fn loaned_payload<H: Header>(sample: &SampleMut<ipc::Service, Self, H>) -> &Self {
        sample.payload()
    }

    fn loaned_payload_mut<H: Header>(sample: &mut SampleMut<ipc::Service, Self, H>) -> &mut Self {
        sample.payload_mut()
    }
}

fn open_event(
    node: &Node<ipc::Service>,
    name: &str,
    qos: &Qos,
) -> Result<iceoryx2::service::port_factory::event::PortFactory<ipc::Service>, PortError> {
    node.service_builder(&service_name(name)?)
        .event()
        .max_notifiers(qos.max_publishers)
        .max_listeners(qos.max_subscribers)
        .max_nodes(qos.max_nodes)
        .open_or_create()
        .map_err(|e| PortError::Open { service: format!("{name} (event)"), reason: format!("{e:?}") })
}

/// What a publisher does when a subscriber's queue is full on a service that does not overflow
/// (on an overflowing service the oldest queued sample is replaced and this does not apply).
/// Whatever is dropped is counted per service and consumer ([`PortStats::undelivered_by`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Delivery {
    /// Drop the new sample for that subscriber and go on: a live source never blocks.
    DiscardWhenFull,
    /// Wait (sleeping, never spinning) until the subscriber has room for as long as its process
    /// is alive (checked every [`LIVENESS_CHECK`]); a dead subscriber, a termination signal or
    /// `max_wait` (if set) drops the sample for it. Replay "as fast as possible" with
    /// back-pressure: a slow consumer slows the source down and loses nothing; a hung one is
    /// the supervisor's to kill, after which the source moves on. While it waits the process's
    /// heartbeat goes on from a keep-alive thread, so the wait itself is not taken for a hang.
    WaitWhenFull {
        /// Longest wait for one subscriber before the sample is dropped for it (`None`: as
        /// long as the subscriber's process lives).
        max_wait: Option<Duration>,
    },
}

/// How often a publisher waiting for a full subscriber checks that the subscriber's process is
/// still alive.
pub const LIVENESS_CHECK: Duration = Duration::from_millis(200);

/// Consumer name recorded for deliveries missed because the subscriber had not connected yet.
pub const NOT_CONNECTED: &str = "(not connected yet)";

/// Process-wide back-pressure state: whether some send is waiting (for the keep-alive
/// heartbeats), the termination signal that ends a wait, the total time waited.
pub struct Backpressure {
    config: iceoryx2::config::Config,
    /// Set while some send of this process waits for a full subscriber.
    waiting: Arc<AtomicBool>,
    /// The process's termination signal (0: none).
    signal: Arc<AtomicUsize>,
    /// Total time spent waiting, µs.
    waited_us: AtomicU64,
    /// Waits outside iceoryx2 in progress ([`crate::Runtime::hold_heartbeat`]).
    external_waits: AtomicUsize,
}

impl Backpressure {
    /// Shared state for the outputs of one process.
    pub fn new(config: iceoryx2::config::Config, waiting: Arc<AtomicBool>, signal: Arc<AtomicUsize>) -> Arc<Self> {
        Arc::new(Self { config, waiting, signal, waited_us: AtomicU64::new(0), external_waits: AtomicUsize::new(0) })
    }

    /// True while a send waits for a full subscriber (or the stage waits outside iceoryx2).
    pub fn is_waiting(&self) -> bool {
        self.waiting.load(Ordering::Relaxed) || self.external_waits.load(Ordering::Relaxed) > 0
    }

    /// Marks the start of a wait outside iceoryx2; [`Backpressure::end_external_wait`] ends it.
    pub fn begin_external_wait(&self) {
        self.external_waits.fetch_add(1, Ordering::Relaxed);
    }

    /// Marks the end of a wait begun with [`Backpressure::begin_external_wait`].
    pub fn end_external_wait(&self) {
        self.external_waits.fetch_sub(1, Ordering::Relaxed);
    }

    /// Total time the process's sends have waited for full subscribers.
    pub fn waited(&self) -> Duration {
        Duration::from_micros(self.waited_us.load(Ordering::Relaxed))
    }
}

/// One output's state shared with its back-pressure handler (which iceoryx2 calls inside
/// `send`, possibly on every retry): who the subscribers are and for whom the current send
/// dropped its sample.
struct PortBackpressure {
    process: Arc<Backpressure>,
    /// Subscriber port id → (node id, consumer name).
    receivers: Mutex<HashMap<u128, (u128, String)>>,
    /// Receivers the current send dropped its sample for.
    dropped: Mutex<Vec<u128>>,
    /// Elapsed time of the current wait at the last liveness check, ms.
    checked_ms: AtomicU64,
}

impl PortBackpressure {
    fn new(process: Arc<Backpressure>) -> Arc<Self> {
        Arc::new(Self {
            process,
            receivers: Mutex::new(HashMap::new()),
            dropped: Mutex::new(vec![]),
            checked_ms: AtomicU64::new(0),
        })
    }

    fn dropped_for(&self, receiver: u128) {
        if let Ok(mut d) = self.dropped.lock() {
            d.push(receiver);
        }
    }

    /// True unless the receiver's node is known and no longer alive.
    fn receiver_alive(&self, receiver: u128) -> bool {
        let Some(node) = self.receivers.lock().ok().and_then(|r| r.get(&receiver).map(|(n, _)| *n)) else {
            return true; // not known yet: a new subscriber
        };
        let mut state = None;
        let listed = Node::<ipc::Service>::list(&self.process.config, |s| {
            if s.node_id().value() == node {
                state = Some(matches!(s, NodeState::Alive(_)));
                CallbackProgression::Stop
            } else {
                CallbackProgression::Continue
            }
        });
        // A node that is gone (cleaned up) or dead is not coming back; an unreadable list is no
        // reason to drop.
        listed.is_err() || state.unwrap_or(false)
    }

    fn wait(
        &self,
        info: &iceoryx2::port::BackpressureInfo,
        max_wait: Option<Duration>,
    ) -> iceoryx2::port::BackpressureAction {
        use iceoryx2::port::BackpressureAction::{DiscardData, Retry};
        self.process.waiting.store(true, Ordering::Relaxed);
        if info.retries == 0 {
            self.checked_ms.store(0, Ordering::Relaxed);
        }
        let elapsed_ms = info.elapsed_time.as_millis() as u64;
        let give_up = self.process.signal.load(Ordering::Relaxed) != 0
            || max_wait.is_some_and(|m| info.elapsed_time >= m)
            || (elapsed_ms >= self.checked_ms.load(Ordering::Relaxed) + LIVENESS_CHECK.as_millis() as u64 && {
                self.checked_ms.store(elapsed_ms, Ordering::Relaxed);
                !self.receiver_alive(info.receiver_port_id)
            });
        if give_up {
            self.dropped_for(info.receiver_port_id);
            return DiscardData;
        }
        // 100 µs steps for the first 10 ms (a short queue drains fast), then 1 ms.
        let step = if info.elapsed_time < Duration::from_millis(10) { 100 } else { 1000 };
        std::thread::sleep(Duration::from_micros(step));
        self.process.waited_us.fetch_add(step, Ordering::Relaxed);
        Retry
    }
}

/// A publisher with its notifier, or (under [`crate::testing`]) an in-process queue.
pub struct Output<P: Payload + ?Sized, H: Header> {
    service: String,
    stats: Rc<RefCell<PortStats>>,
    seq: u64,
    link: OutLink<P, H>,
}

enum OutLink<P: Payload + ?Sized, H: Header> {
    Shm(Box<ShmOutput<P, H>>),
    Local(Rc<LocalQueue<P, H>>),
}

/// The iceoryx2 side of an [`Output`].
struct ShmOutput<P: Payload + ?Sized, H: Header> {
    factory: PortFactory<ipc::Service, P, H>,
    publisher: Publisher<ipc::Service, P, H>,
    notifier: Notifier<ipc::Service>,
    bp: Arc<PortBackpressure>,
    /// Subscriber count when the receivers' names were last read.
    known_subscribers: Option<usize>,
    /// Every consumer that has subscribed to this service: one that is gone misses what is
    /// sent meanwhile.
    expected: std::collections::BTreeSet<String>,
}

impl<P: Payload + ?Sized, H: Header> Output<P, H> {
    /// Service name.
    pub fn service(&self) -> &str {
        &self.service
    }

    /// Sequence number the next message will carry.
    pub fn next_seq(&self) -> u64 {
        self.seq
    }

    /// Messages sent so far.
    pub fn sent(&self) -> u64 {
        self.seq
    }

    /// Counts `n` messages meant for this output that the stage dropped before it could publish
    /// them (a bridge: refused or lost on the way), for `reason`: shown like an input's drops
    /// (status line `DROPPED`, warning, summary.json `dropped`).
    pub fn count_dropped(&self, reason: &str, n: u64) {
        if n > 0 {
            *self.stats.borrow_mut().dropped_by.entry(reason.to_string()).or_default() += n;
        }
    }

    /// Wakes the subscribers without sending data: a woken subscriber attaches to this publisher
    /// (a source calls this while it waits for its subscribers before the first message).
    pub fn nudge(&self) -> Result<(), PortError> {
        match &self.link {
            OutLink::Shm(o) => o.notifier.notify().map(|_| ()).map_err(|e| io_err(&self.service, "notify", e)),
            OutLink::Local(_) => Ok(()),
        }
    }

    /// Subscribers currently registered on the service (connected or not yet); an in-process
    /// output has one, its test.
    pub fn subscribers(&self) -> usize {
        match &self.link {
            OutLink::Shm(o) => o.subscribers(),
            OutLink::Local(_) => 1,
        }
    }

    /// Stamps `seq`, `publish_ns` (and `origin_ns = publish_ns` when it is 0), sends and wakes
    /// the subscribers. Returns the number of subscribers that received the sample.
    pub fn send(&mut self, mut sample: Loaned<P, H>) -> Result<usize, PortError> {
        let h = sample.user_header_mut().msg_mut();
        h.seq = self.seq;
        h.publish_ns = monotonic_ns();
        if h.origin_ns == 0 {
            h.origin_ns = h.publish_ns;
        }
        let n = match (&mut self.link, sample) {
            (OutLink::Shm(o), Loaned::Shm(sample)) => o.send(sample, &self.service, &self.stats)?,
            (OutLink::Local(q), Loaned::Local(header, payload)) => {
                q.borrow_mut().push_back((header, payload));
                self.stats.borrow_mut().count += 1;
                1
            }
            _ => {
                return Err(PortError::Io {
                    service: self.service.clone(),
                    op: "send",
                    reason: "the sample was loaned from another kind of port".into(),
                });
            }
        };
        self.seq += 1;
        Ok(n)
    }
}

impl<P: Payload + ?Sized, H: Header> ShmOutput<P, H> {
    /// Reads the subscribers' port ids, nodes and names (the consumer a dropped sample is
    /// counted for).
    fn refresh_receivers(&self) {
        let mut map = HashMap::new();
        iceoryx2::service::port_factory::PortFactory::dynamic_config(&self.factory).list_subscribers(|d| {
            let name = d.subscriber_name.as_str();
            let name = if name.is_empty() { format!("node {:x}", d.node_id.value()) } else { name.to_string() };
            map.insert(d.subscriber_id.value(), (d.node_id.value(), name));
            CallbackProgression::Continue
        });
        if let Ok(mut r) = self.bp.receivers.lock() {
            *r = map;
        }
    }

    fn subscribers(&self) -> usize {
        iceoryx2::service::port_factory::PortFactory::dynamic_config(&self.factory).number_of_subscribers()
    }

    /// Sends a stamped sample and wakes the subscribers; counts what did not reach whom.
    fn send(
        &mut self,
        sample: SampleMut<ipc::Service, P, H>,
        service: &str,
        stats: &RefCell<PortStats>,
    ) -> Result<usize, PortError> {
        let subscribers = self.subscribers();
        if self.known_subscribers != Some(subscribers) {
            self.refresh_receivers();
            self.known_subscribers = Some(subscribers);
        }
        let before: HashMap<u128, (u128, String)> = self.bp.receivers.lock().map(|r| r.clone()).unwrap_or_default();
        let sent = sample.send();
        self.bp.process.waiting.store(false, Ordering::Relaxed);
        let n = sent.map_err(|e| io_err(service, "send", e))?;
        let dropped: Vec<u128> = self.bp.dropped.lock().map(|mut d| std::mem::take(&mut *d)).unwrap_or_default();
        // Subscribers that went away during the send (a consumer died while we waited for it).
        let after = self.subscribers();
        if after != subscribers {
            self.refresh_receivers();
            self.known_subscribers = Some(after);
        }
        let now: std::collections::HashSet<String> =
            self.bp.receivers.lock().map(|r| r.values().map(|(_, n)| n.clone()).collect()).unwrap_or_default();
        {
            let mut st = stats.borrow_mut();
            st.count += 1;
            let mut missed: Vec<String> = dropped
                .iter()
                .map(|id| before.get(id).map(|(_, n)| n.clone()).unwrap_or_else(|| format!("port {id:x}")))
                .collect();
            for (id, (_, name)) in &before {
                if !now.contains(name) && !dropped.contains(id) {
                    missed.push(name.clone());
                }
            }
            // The rest reached no subscriber because it had not connected to this publisher yet.
            let unconnected = subscribers.saturating_sub(n).saturating_sub(missed.len());
            missed.extend(std::iter::repeat_n(NOT_CONNECTED.to_string(), unconnected));
            // Consumers seen before that are gone: they miss this message too (until they are
            // back, e.g. restarted).
            for name in &self.expected {
                if !now.contains(name) && !before.values().any(|(_, b)| b == name) {
                    missed.push(name.clone());
                }
            }
            st.undelivered += missed.len() as u64;
            for name in missed {
                *st.undelivered_by.entry(name).or_default() += 1;
            }
        }
        self.expected.extend(now);
        self.notifier.notify().map_err(|e| io_err(service, "notify", e))?;
        Ok(n)
    }
}

impl<P: Payload + ?Sized, H: Header> Output<P, H> {
    fn assemble(
        node: &Node<ipc::Service>,
        name: &str,
        qos: &Qos,
        factory: PortFactory<ipc::Service, P, H>,
        publisher: Publisher<ipc::Service, P, H>,
        stats: Rc<RefCell<PortStats>>,
        bp: Arc<PortBackpressure>,
    ) -> Result<Self, PortError> {
        let notifier = open_event(node, name, qos)?
            .notifier_builder()
            .create()
            .map_err(|e| PortError::Create { service: format!("{name} (event)"), reason: format!("{e:?}") })?;
        Ok(Self {
            service: name.to_string(),
            stats,
            seq: 0,
            link: OutLink::Shm(Box::new(ShmOutput {
                factory,
                publisher,
                notifier,
                bp,
                known_subscribers: None,
                expected: Default::default(),
            })),
        })
    }

    /// An in-process output: what is sent is queued on `queue` (see [`crate::testing`]).
    pub(crate) fn local(service: &str, queue: Rc<LocalQueue<P, H>>, stats: Rc<RefCell<PortStats>>) -> Self {
        Self { service: service.to_string(), stats, seq: 0, link: OutLink::Local(queue) }
    }
}

impl<T: Debug + ZeroCopySend + Copy + 'static, H: Header> Output<T, H> {
    /// Creates a publisher of fixed-size values on `name` with `qos`.
    pub fn create(
        node: &Node<ipc::Service>,
        name: &str,
        qos: &Qos,
        delivery: Delivery,
        stats: Rc<RefCell<PortStats>>,
        bp: Arc<Backpressure>,
    ) -> Result<Self, PortError> {
        let factory = T::open_service::<H>(node, name, qos)?;
        let builder = factory.publisher_builder().max_loaned_samples(qos.publisher_loans);
        let bp = PortBackpressure::new(bp);
        let publisher = with_delivery!(builder, delivery, bp)
            .create()
            .map_err(|e| PortError::Create { service: name.to_string(), reason: format!("{e:?}") })?;
        Self::assemble(node, name, qos, factory, publisher, stats, bp)
    }

    /// Loans an uninitialised sample in shared memory (write it in place, then [`Output::send`]).
    pub fn loan_uninit(&self) -> Result<Loan<T, H>, PortError> {
        match &self.link {
            OutLink::Shm(o) => o.publisher.loan_uninit().map(Loan::Shm).map_err(|e| io_err(&self.service, "loan", e)),
            OutLink::Local(_) => Ok(Loan::Local(H::default())),
        }
    }

    /// Sends `value` with `header` (its `seq`/`publish_ns` are overwritten).
    pub fn send_value(&mut self, header: H, value: T) -> Result<usize, PortError> {
        let mut sample = self.loan_uninit()?.write_payload(value);
        *sample.user_header_mut() = header;
        self.send(sample)
    }
}

impl<T: Debug + ZeroCopySend + Copy + 'static, H: Header> Output<[T], H> {
    /// Creates a publisher of slices on `name` with `qos`; it reserves `qos.initial_slice_len`
    /// elements per sample and grows by powers of two when a larger slice is loaned.
    pub fn create_slice(
        node: &Node<ipc::Service>,
        name: &str,
        qos: &Qos,
        stats: Rc<RefCell<PortStats>>,
        bp: Arc<Backpressure>,
    ) -> Result<Self, PortError> {
        Self::create_slice_with_len(node, name, qos, qos.initial_slice_len.max(1), Delivery::DiscardWhenFull, stats, bp)
    }

    /// As [`Output::create_slice`] with an explicit initial slice length.
    #[allow(clippy::too_many_arguments)]
    pub fn create_slice_with_len(
        node: &Node<ipc::Service>,
        name: &str,
        qos: &Qos,
        initial_len: usize,
        delivery: Delivery,
        stats: Rc<RefCell<PortStats>>,
        bp: Arc<Backpressure>,
    ) -> Result<Self, PortError> {
        let factory = <[T]>::open_service::<H>(node, name, qos)?;
        let builder = factory
            .publisher_builder()
            .initial_max_slice_len(initial_len.max(1))
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .max_loaned_samples(qos.publisher_loans);
        let bp = PortBackpressure::new(bp);
        let publisher = with_delivery!(builder, delivery, bp)
            .create()
            .map_err(|e| PortError::Create { service: name.to_string(), reason: format!("{e:?}") })?;
        Self::assemble(node, name, qos, factory, publisher, stats, bp)
    }

    /// Loans an uninitialised slice of `len` elements in shared memory; fill it in place with
    /// `write_from_fn` (or through `payload_mut`), set the header, then [`Output::send`].
    pub fn loan_slice_uninit(&self, len: usize) -> Result<SliceLoan<T, H>, PortError> {
        match &self.link {
            OutLink::Shm(o) => {
                o.publisher.loan_slice_uninit(len).map(SliceLoan::Shm).map_err(|e| io_err(&self.service, "loan", e))
            }
            OutLink::Local(_) => Ok(SliceLoan::Local(H::default(), Box::new_uninit_slice(len))),
        }
    }
}

/// A subscriber with the listener of its event service, or (under [`crate::testing`]) an
/// in-process queue.
pub struct Input<P: Payload + ?Sized, H: Header> {
    service: String,
    link: InLink<P, H>,
    stats: Rc<RefCell<PortStats>>,
}

enum InLink<P: Payload + ?Sized, H: Header> {
    Shm { subscriber: Rc<Subscriber<ipc::Service, P, H>>, listener: Rc<Listener<ipc::Service>> },
    Local(Rc<LocalQueue<P, H>>),
}

impl<P: Payload + ?Sized, H: Header> Input<P, H> {
    /// Creates a subscriber on `name` with `qos` holding at most `buffer` samples (at most the
    /// service's `qos.subscriber_buffer`), named after its node (the consumer a publisher counts
    /// dropped samples for).
    pub fn create(
        node: &Node<ipc::Service>,
        name: &str,
        qos: &Qos,
        buffer: usize,
        stats: Rc<RefCell<PortStats>>,
    ) -> Result<Self, PortError> {
        let factory = P::open_service::<H>(node, name, qos)?;
        let mut builder = factory.subscriber_builder().buffer_size(buffer.clamp(1, qos.subscriber_buffer));
        if let Ok(port_name) = iceoryx2::port::port_name::PortName::new(node.name().as_str()) {
            builder = builder.name(&port_name);
        }
        let subscriber = builder.create().map_err(|e| {
            let mut reason = format!("{e:?}");
            if reason.contains("ExceedsMaxSupportedSubscribers") {
                let q = qos;
                reason += &format!(
                    " (it admits {} subscribers, all taken by other processes of this run or tools attached to it; \
                     raise `run.extra_subscribers`)",
                    q.max_subscribers
                );
            }
            PortError::Create { service: name.to_string(), reason }
        })?;
        let listener = open_event(node, name, qos)?
            .listener_builder()
            .create()
            .map_err(|e| PortError::Create { service: format!("{name} (event)"), reason: format!("{e:?}") })?;
        Ok(Self {
            service: name.to_string(),
            link: InLink::Shm { subscriber: Rc::new(subscriber), listener: Rc::new(listener) },
            stats,
        })
    }

    /// An in-process input: it receives what is queued on `queue` (see [`crate::testing`]).
    pub(crate) fn local(service: &str, queue: Rc<LocalQueue<P, H>>, stats: Rc<RefCell<PortStats>>) -> Self {
        Self { service: service.to_string(), link: InLink::Local(queue), stats }
    }

    /// Service name.
    pub fn service(&self) -> &str {
        &self.service
    }

    /// A handle that attaches this subscriber to publishers that appeared since the last call.
    /// iceoryx2 connects a subscriber only when it acts (receive, or this), and a publisher's
    /// samples to a subscriber that has not connected yet fill a short buffer and are then lost;
    /// the runtime therefore calls this on every loop iteration. `None` for an in-process input.
    pub fn connector(&self) -> Option<Rc<dyn Fn()>> {
        let InLink::Shm { subscriber, .. } = &self.link else { return None };
        let sub = subscriber.clone();
        Some(Rc::new(move || {
            if let Err(e) = iceoryx2::port::update_connections::UpdateConnections::update_connections(&*sub) {
                tracing::debug!("update_connections: {e:?}");
            }
        }))
    }

    /// The listener the WaitSet attaches to (`None` for an in-process input).
    pub fn listener(&self) -> Option<Rc<Listener<ipc::Service>>> {
        match &self.link {
            InLink::Shm { listener, .. } => Some(listener.clone()),
            InLink::Local(_) => None,
        }
    }

    /// Messages received so far.
    pub fn received(&self) -> u64 {
        self.stats.borrow().count
    }

    /// Counts `n` messages of this input that the stage dropped (or missed: a gap in the
    /// publisher's sequence numbers) for `reason`. Nothing is lost silently: the supervisor shows
    /// them in the status line (`DROPPED`), warns once per process, service and reason at the end
    /// of the run and lists them in summary.json (`dropped`).
    pub fn count_dropped(&self, reason: &str, n: u64) {
        if n > 0 {
            *self.stats.borrow_mut().dropped_by.entry(reason.to_string()).or_default() += n;
        }
    }

    /// Tells the runtime that the newest `n` messages the stage received from this input are not
    /// kept yet: unprocessed in its own queue, or processed into state a restart would not get
    /// back (the mapper's clouds since its last checkpoint). A restarted instance resumes before
    /// them: if the process is killed, they count as lost in the restart, as what sat in the
    /// service's queue does (exact for a service with one publisher, the pipeline's own case).
    pub fn set_held(&self, n: u64) {
        let mut st = self.stats.borrow_mut();
        if st.held != n {
            st.held = n;
            st.seq_dirty = true;
        }
    }

    /// Messages dropped so far, over all reasons.
    pub fn dropped(&self) -> u64 {
        self.stats.borrow().dropped_by.values().sum()
    }

    /// Receives the next sample (recording its latency), or `None` when the queue is empty.
    pub fn receive(&self) -> Result<Option<Received<P, H>>, PortError> {
        let s = match &self.link {
            InLink::Shm { subscriber, .. } => P::receive_shm(subscriber, &self.service)?.map(Received::Shm),
            InLink::Local(q) => q.borrow_mut().pop_front().map(|(h, p)| Received::Local(h, p)),
        };
        if let Some(s) = &s {
            let h = s.user_header().msg();
            let mut stats = self.stats.borrow_mut();
            stats.record_receive(monotonic_ns(), h.publish_ns, h.origin_ns);
            stats.note_seq(s.publisher_id(), h.seq);
        }
        Ok(s)
    }
}

/// Queued messages of one in-process service: header and owned payload.
pub(crate) type LocalQueue<P, H> = RefCell<VecDeque<(H, Box<P>)>>;

/// Which side of an in-process service a queue is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub(crate) enum Side {
    /// What one of the stage's inputs reads (fed by the test): every input has its own queue,
    /// as every iceoryx2 subscriber receives its own copy.
    Input,
    /// What the stage's outputs send (taken by the test): one queue per service.
    Output,
}

/// In-process queues that stand in for iceoryx2 services when a stage runs under
/// [`crate::testing::StageHarness`], typed by the service's first user.
#[derive(Default)]
pub(crate) struct LocalBus {
    inputs: RefCell<HashMap<String, Vec<Rc<dyn Any>>>>,
    outputs: RefCell<HashMap<String, Rc<dyn Any>>>,
}

fn downcast<P: ?Sized + 'static, H: 'static>(
    service: &str,
    any: Rc<dyn Any>,
) -> Result<Rc<LocalQueue<P, H>>, PortError> {
    any.downcast::<LocalQueue<P, H>>().map_err(|_| PortError::Open {
        service: service.to_string(),
        reason: format!(
            "opened before with another payload or header type than {} / {}",
            std::any::type_name::<P>(),
            std::any::type_name::<H>()
        ),
    })
}

impl LocalBus {
    /// A queue of `service`: a new one for an input (`Side::Input`), the service's one for an
    /// output; an error when the service was first used with another payload or header type
    /// (as iceoryx2 refuses a service opened with another type).
    pub(crate) fn queue<P: ?Sized + 'static, H: 'static>(
        &self,
        service: &str,
        side: Side,
    ) -> Result<Rc<LocalQueue<P, H>>, PortError> {
        match side {
            Side::Input => {
                let mut inputs = self.inputs.borrow_mut();
                let list = inputs.entry(service.to_string()).or_default();
                if let Some(first) = list.first() {
                    downcast::<P, H>(service, first.clone())?;
                }
                let q = Rc::new(LocalQueue::<P, H>::default());
                list.push(q.clone() as Rc<dyn Any>);
                Ok(q)
            }
            Side::Output => {
                let any = self
                    .outputs
                    .borrow_mut()
                    .entry(service.to_string())
                    .or_insert_with(|| Rc::new(LocalQueue::<P, H>::default()) as Rc<dyn Any>)
                    .clone();
                downcast(service, any)
            }
        }
    }

    /// The queues of every input on `service` (empty when the stage has none).
    pub(crate) fn inputs<P: ?Sized + 'static, H: 'static>(
        &self,
        service: &str,
    ) -> Result<Vec<Rc<LocalQueue<P, H>>>, PortError> {
        let inputs = self.inputs.borrow();
        inputs.get(service).into_iter().flatten().map(|q| downcast(service, q.clone())).collect()
    }
}
