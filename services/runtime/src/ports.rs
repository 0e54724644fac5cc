//! Typed ports: a publisher paired with the notifier of its event service ([`Output`]), and a
//! subscriber paired with a listener the process's WaitSet blocks on ([`Input`]).
//!
//! Every port is created with the QoS of its [`ServiceSpec`](shared_types::services::ServiceSpec),
//! set explicitly. [`Output::send`] stamps `seq` and `publish_ns` (and `origin_ns` when the caller
//! left it 0, i.e. for sensor sources), sends and notifies. [`Input`] receives and records hop and
//! end-to-end latency into the port's histograms before handing the sample to the caller.

use std::cell::RefCell;
use std::collections::HashMap;
use std::fmt::Debug;
use std::mem::MaybeUninit;
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
}

macro_rules! open_with_qos {
    ($builder:expr, $name:expr, $qos:expr) => {
        $builder
            .max_publishers($qos.max_publishers)
            .max_subscribers($qos.max_subscribers)
            .max_nodes($qos.max_nodes)
            .subscriber_max_buffer_size($qos.subscriber_buffer)
            .subscriber_max_borrowed_samples($qos.subscriber_borrowed)
            .history_size($qos.history)
            .enable_safe_overflow($qos.safe_overflow)
            .open_or_create()
            .map_err(|e| PortError::Open { service: $name.to_string(), reason: format!("{e:?}") })
    };
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
}

impl Backpressure {
    /// Shared state for the outputs of one process.
    pub fn new(config: iceoryx2::config::Config, waiting: Arc<AtomicBool>, signal: Arc<AtomicUsize>) -> Arc<Self> {
        Arc::new(Self { config, waiting, signal, waited_us: AtomicU64::new(0) })
    }

    /// True while a send waits for a full subscriber.
    pub fn is_waiting(&self) -> bool {
        self.waiting.load(Ordering::Relaxed)
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

/// A publisher with its notifier.
pub struct Output<P: Payload + ?Sized, H: Header> {
    service: String,
    factory: PortFactory<ipc::Service, P, H>,
    publisher: Publisher<ipc::Service, P, H>,
    notifier: Notifier<ipc::Service>,
    stats: Rc<RefCell<PortStats>>,
    seq: u64,
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

    /// Wakes the subscribers without sending data: a woken subscriber attaches to this publisher
    /// (a source calls this while it waits for its subscribers before the first message).
    pub fn nudge(&self) -> Result<(), PortError> {
        self.notifier.notify().map(|_| ()).map_err(|e| io_err(&self.service, "notify", e))
    }

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

    /// Subscribers currently registered on the service (connected or not yet).
    pub fn subscribers(&self) -> usize {
        iceoryx2::service::port_factory::PortFactory::dynamic_config(&self.factory).number_of_subscribers()
    }

    /// Stamps `seq`, `publish_ns` (and `origin_ns = publish_ns` when it is 0), sends and wakes
    /// the subscribers. Returns the number of subscribers that received the sample.
    pub fn send(&mut self, mut sample: SampleMut<ipc::Service, P, H>) -> Result<usize, PortError>
    where
        P: IceoryxSend,
    {
        let h = sample.user_header_mut().msg_mut();
        h.seq = self.seq;
        h.publish_ns = monotonic_ns();
        if h.origin_ns == 0 {
            h.origin_ns = h.publish_ns;
        }
        let subscribers = self.subscribers();
        if self.known_subscribers != Some(subscribers) {
            self.refresh_receivers();
            self.known_subscribers = Some(subscribers);
        }
        let before: HashMap<u128, (u128, String)> = self.bp.receivers.lock().map(|r| r.clone()).unwrap_or_default();
        let sent = sample.send();
        self.bp.process.waiting.store(false, Ordering::Relaxed);
        let n = sent.map_err(|e| io_err(&self.service, "send", e))?;
        self.seq += 1;
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
            let mut st = self.stats.borrow_mut();
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
        self.notifier.notify().map_err(|e| io_err(&self.service, "notify", e))?;
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
            factory,
            publisher,
            notifier,
            stats,
            seq: 0,
            bp,
            known_subscribers: None,
            expected: Default::default(),
        })
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
    pub fn loan_uninit(&self) -> Result<SampleMutUninit<ipc::Service, MaybeUninit<T>, H>, PortError> {
        self.publisher.loan_uninit().map_err(|e| io_err(&self.service, "loan", e))
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
    pub fn loan_slice_uninit(
        &self,
        len: usize,
    ) -> Result<SampleMutUninit<ipc::Service, [MaybeUninit<T>], H>, PortError> {
        self.publisher.loan_slice_uninit(len).map_err(|e| io_err(&self.service, "loan", e))
    }
}

/// A subscriber with the listener of its event service.
pub struct Input<P: Payload + ?Sized, H: Header> {
    service: String,
    subscriber: Rc<Subscriber<ipc::Service, P, H>>,
    listener: Rc<Listener<ipc::Service>>,
    stats: Rc<RefCell<PortStats>>,
}

impl<P: Payload + ?Sized, H: Header> Input<P, H> {
    /// Creates a subscriber on `name` with `qos`, named after its node (the consumer a
    /// publisher counts dropped samples for).
    pub fn create(
        node: &Node<ipc::Service>,
        name: &str,
        qos: &Qos,
        stats: Rc<RefCell<PortStats>>,
    ) -> Result<Self, PortError> {
        let factory = P::open_service::<H>(node, name, qos)?;
        let mut builder = factory.subscriber_builder().buffer_size(qos.subscriber_buffer);
        if let Ok(port_name) = iceoryx2::port::port_name::PortName::new(node.name().as_str()) {
            builder = builder.name(&port_name);
        }
        let subscriber =
            builder.create().map_err(|e| PortError::Create { service: name.to_string(), reason: format!("{e:?}") })?;
        let listener = open_event(node, name, qos)?
            .listener_builder()
            .create()
            .map_err(|e| PortError::Create { service: format!("{name} (event)"), reason: format!("{e:?}") })?;
        Ok(Self { service: name.to_string(), subscriber: Rc::new(subscriber), listener: Rc::new(listener), stats })
    }

    /// Service name.
    pub fn service(&self) -> &str {
        &self.service
    }

    /// A handle that attaches this subscriber to publishers that appeared since the last call.
    /// iceoryx2 connects a subscriber only when it acts (receive, or this), and a publisher's
    /// samples to a subscriber that has not connected yet fill a short buffer and are then lost;
    /// the runtime therefore calls this on every loop iteration.
    pub fn connector(&self) -> Rc<dyn Fn()> {
        let sub = self.subscriber.clone();
        Rc::new(move || {
            if let Err(e) = iceoryx2::port::update_connections::UpdateConnections::update_connections(&*sub) {
                tracing::debug!("update_connections: {e:?}");
            }
        })
    }

    /// The listener the WaitSet attaches to.
    pub fn listener(&self) -> Rc<Listener<ipc::Service>> {
        self.listener.clone()
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

    /// Messages dropped so far, over all reasons.
    pub fn dropped(&self) -> u64 {
        self.stats.borrow().dropped_by.values().sum()
    }

    fn record(&self, sample: &Sample<ipc::Service, P, H>) {
        let h = sample.user_header().msg();
        self.stats.borrow_mut().record_receive(monotonic_ns(), h.publish_ns, h.origin_ns);
    }
}

impl<T: Debug + ZeroCopySend + 'static, H: Header> Input<T, H> {
    /// Receives the next sample (recording its latency), or `None` when the queue is empty.
    pub fn receive(&self) -> Result<Option<Sample<ipc::Service, T, H>>, PortError> {
        let s = self.subscriber.receive().map_err(|e| io_err(&self.service, "receive", e))?;
        if let Some(s) = &s {
            self.record(s);
        }
        Ok(s)
    }
}

impl<T: Debug + ZeroCopySend + 'static, H: Header> Input<[T], H> {
    /// Receives the next slice sample (recording its latency), or `None` when the queue is empty.
    pub fn receive(&self) -> Result<Option<Sample<ipc::Service, [T], H>>, PortError> {
        let s = self.subscriber.receive().map_err(|e| io_err(&self.service, "receive", e))?;
        if let Some(s) = &s {
            self.record(s);
        }
        Ok(s)
    }
}
