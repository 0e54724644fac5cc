//! The links of a chain: names, QoS, and the bare-iceoryx2 endpoint (one publisher + notifier, one
//! subscriber + listener, a WaitSet with the listener only), the reference the runtime's own hop
//! is compared with.
//!
//! A chain of `n` relays has `n + 1` links: link 0 from the producer to relay 1, link `k` from
//! relay `k` to relay `k + 1`, and link `n` from relay `n` back to the producer.

use std::mem::MaybeUninit;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context as _, anyhow};
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;
use iceoryx2::sample_mut::SampleMut;
use pipeline_runtime::IoxScope;
use shared_types::MsgHeader;
use shared_types::services::Qos;

/// Payload type of every iceoryx2 link: bytes that need not be initialised (a relay writes only
/// the 16 index bytes of its output, see [`super::wire`]).
pub type Bytes = MaybeUninit<u8>;

/// iceoryx2 service name of link `k` of a case.
pub fn link_service(case: &str, k: usize) -> String {
    format!("bench/latency/{case}/link{k}")
}

/// Socket path of link `k` of a case (the receiving side listens on it).
pub fn link_socket(dir: &Path, case: &str, k: usize) -> PathBuf {
    dir.join(format!("{case}-link{k}.sock"))
}

/// QoS of a link: one publisher, one subscriber, two queued samples (at most one is in flight),
/// one borrowed and one loaned sample, no history, newest wins; slices of `size` bytes reserved
/// up front so nothing grows during the measurement.
pub fn link_qos(size: usize) -> Qos {
    Qos {
        max_publishers: 1,
        max_subscribers: 1,
        max_nodes: 2,
        subscriber_buffer: 2,
        subscriber_borrowed: 1,
        history: 0,
        safe_overflow: true,
        publisher_loans: 1,
        initial_slice_len: size,
    }
}

/// One process's two ports on bare iceoryx2 (the same QoS as [`link_qos`]).
pub struct BareEndpoint {
    /// Keeps the ports' node alive.
    _node: Node<ipc::Service>,
    publisher: Publisher<ipc::Service, [Bytes], MsgHeader>,
    notifier: Notifier<ipc::Service>,
    subscriber: Subscriber<ipc::Service, [Bytes], MsgHeader>,
    listener: Listener<ipc::Service>,
    waitset: WaitSet<ipc::Service>,
}

fn iox<E: std::fmt::Debug>(what: &str, service: &str) -> impl FnOnce(E) -> anyhow::Error {
    let ctx = format!("{what} {service}");
    move |e| anyhow!("{ctx}: {e:?}")
}

impl BareEndpoint {
    /// Node `name` in `scope`, publishing on `out_service` and subscribed to `in_service`.
    pub fn new(scope: &IoxScope, name: &str, in_service: &str, out_service: &str, size: usize) -> anyhow::Result<Self> {
        let node = scope.create_node(name).with_context(|| format!("creating node {name}"))?;
        let qos = link_qos(size);
        let pubsub = |service: &str| -> anyhow::Result<_> {
            let sn = ServiceName::new(service).map_err(iox("service name", service))?;
            node.service_builder(&sn)
                .publish_subscribe::<[Bytes]>()
                .user_header::<MsgHeader>()
                .max_publishers(qos.max_publishers)
                .max_subscribers(qos.max_subscribers)
                .max_nodes(qos.max_nodes)
                .subscriber_max_buffer_size(qos.subscriber_buffer)
                .subscriber_max_borrowed_samples(qos.subscriber_borrowed)
                .history_size(qos.history)
                .enable_safe_overflow(qos.safe_overflow)
                .open_or_create()
                .map_err(iox("opening", service))
        };
        let event = |service: &str| -> anyhow::Result<_> {
            let sn = ServiceName::new(service).map_err(iox("service name", service))?;
            node.service_builder(&sn)
                .event()
                .max_notifiers(qos.max_publishers)
                .max_listeners(qos.max_subscribers)
                .max_nodes(qos.max_nodes)
                .open_or_create()
                .map_err(iox("opening the event service", service))
        };
        let publisher = pubsub(out_service)?
            .publisher_builder()
            .initial_max_slice_len(size)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .max_loaned_samples(qos.publisher_loans)
            .create()
            .map_err(iox("creating the publisher of", out_service))?;
        let notifier = event(out_service)?.notifier_builder().create().map_err(iox("notifier of", out_service))?;
        let subscriber = pubsub(in_service)?
            .subscriber_builder()
            .buffer_size(qos.subscriber_buffer)
            .create()
            .map_err(iox("creating the subscriber of", in_service))?;
        let listener = event(in_service)?.listener_builder().create().map_err(iox("listener of", in_service))?;
        let waitset = WaitSetBuilder::new()
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .map_err(|e| anyhow!("creating a WaitSet: {e:?}"))?;
        Ok(Self { _node: node, publisher, notifier, subscriber, listener, waitset })
    }

    /// The loop of a process on this endpoint: blocks in the WaitSet (listener attached once) until
    /// the listener is notified or the timeout passes, drains the listener, then calls `step` with
    /// whether it was notified. `step` returns the next timeout, or `None` to leave the loop.
    pub fn run(
        &self,
        first_timeout: Duration,
        mut step: impl FnMut(bool) -> anyhow::Result<Option<Duration>>,
    ) -> anyhow::Result<()> {
        let guard = self.waitset.attach_notification(&self.listener).map_err(|e| anyhow!("attach: {e:?}"))?;
        let mut timeout = first_timeout;
        loop {
            let mut woke = false;
            self.waitset
                .wait_and_process_once_with_timeout(
                    |id| {
                        if id.has_event_from(&guard) {
                            let _ = self.listener.try_wait(|_| {});
                            woke = true;
                        }
                        CallbackProgression::Continue
                    },
                    timeout,
                )
                .map_err(|e| anyhow!("WaitSet wait: {e:?}"))?;
            match step(woke)? {
                Some(t) => timeout = t,
                None => return Ok(()),
            }
        }
    }

    /// The next received sample, if any.
    pub fn receive(&self) -> anyhow::Result<Option<Sample<ipc::Service, [Bytes], MsgHeader>>> {
        self.subscriber.receive().map_err(|e| anyhow!("receive: {e:?}"))
    }

    /// Loans a `len`-byte sample (its bytes need not be initialised).
    pub fn loan(&self, len: usize) -> anyhow::Result<SampleMut<ipc::Service, [Bytes], MsgHeader>> {
        let sample = self.publisher.loan_slice_uninit(len).map_err(|e| anyhow!("loan: {e:?}"))?;
        // SAFETY: the payload type is `MaybeUninit<u8>`, so `MaybeUninit<MaybeUninit<u8>>` holds a
        // valid value whatever its bytes are.
        Ok(unsafe { sample.assume_init() })
    }

    /// Sends and notifies; returns the subscribers reached.
    pub fn send(&self, sample: SampleMut<ipc::Service, [Bytes], MsgHeader>) -> anyhow::Result<usize> {
        let n = sample.send().map_err(|e| anyhow!("send: {e:?}"))?;
        self.notifier.notify().map_err(|e| anyhow!("notify: {e:?}"))?;
        Ok(n)
    }
}
