//! The process runtime: one iceoryx2 node, typed ports, and a WaitSet loop that blocks until data
//! arrives or an interval tick fires (never spins), returns on SIGINT/SIGTERM, and on the side
//! publishes the heartbeat and the latency statistics.
//!
//! A process is `main` → [`ProcessContext::from_args`] → [`Runtime::new`] → create ports →
//! [`Runtime::run`] with a handler that drains its inputs and calls the process's pure `step`.

use std::cell::RefCell;
use std::fmt::Debug;
use std::path::PathBuf;
use std::rc::Rc;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use iceoryx2::port::listener::Listener;
use iceoryx2::prelude::*;
use shared_types::services::{self, Qos};
use shared_types::{EndOfStream, Heartbeat, MsgHeader, name32};

use crate::clock::monotonic_ns;
use crate::config::{LogFormat, PipelineConfig, ProcessSettings, load_pipeline_config, settings_for};
pub use crate::error::RuntimeError;
use crate::error::{ContextError, StageError};
use crate::iox::IoxScope;
use crate::ports::{Backpressure, Delivery, Header, Input, LocalBus, Output, PortError, Side};
use crate::stats::{PortStats, StatsReport};

/// Command line shared by every pipeline process.
#[derive(Debug, Clone, clap::Parser)]
pub struct ProcessArgs {
    /// The pipeline config file (the same file the supervisor runs).
    #[arg(long)]
    pub config: PathBuf,
    /// This process's name: its table under `[processes]`.
    #[arg(long)]
    pub name: String,
    /// Log format (default: the config's `run.log_format`).
    #[arg(long, value_enum)]
    pub log_format: Option<LogFormat>,
    /// Validate this process's settings and print the verdict as JSON on stdout (see
    /// [`crate::protocol`]), then exit without starting.
    #[arg(long)]
    pub check: bool,
}

/// Everything a process knows about its run before it opens any port.
#[derive(Debug, Clone)]
pub struct ProcessContext {
    /// Process name.
    pub name: String,
    /// The whole pipeline config.
    pub config: PipelineConfig,
    /// The iceoryx2 scope (from the supervisor's environment, else from the config).
    pub scope: IoxScope,
    /// Where this process writes its output files: the run's directory, or the process's own
    /// `out_dir` inside it.
    pub out_dir: PathBuf,
    /// The run's output directory (summary parts, restart state, statistics).
    pub run_dir: PathBuf,
    /// Log format in effect.
    pub log_format: LogFormat,
}

impl ProcessContext {
    /// Loads the config and resolves the scope. Errors name the file and key.
    pub fn from_args(args: &ProcessArgs) -> Result<Self, ContextError> {
        let config = load_pipeline_config(&args.config)?;
        if !config.processes.contains_key(&args.name) {
            return Err(ContextError::NoProcess { file: args.config.clone(), name: args.name.clone() });
        }
        let scope = IoxScope::from_env().unwrap_or_else(|| IoxScope {
            prefix: config.run.iceoryx_prefix.clone(),
            root: config.iceoryx_root(),
            base_config: config.iceoryx_config_file(),
        });
        let run_dir = std::env::var_os(ENV_OUT_DIR).map(PathBuf::from).unwrap_or_else(|| config.run.out_dir.clone());
        let out_dir = match &config.processes[&args.name].out_dir {
            Some(own) => run_dir.join(own),
            None => run_dir.clone(),
        };
        let log_format = args.log_format.unwrap_or(config.run.log_format);
        Ok(Self { name: args.name.clone(), config, scope, out_dir, run_dir, log_format })
    }

    /// This process's typed, validated settings.
    pub fn settings<T: ProcessSettings>(&self) -> Result<T, ContextError> {
        let table = &self.config.processes[&self.name].settings;
        settings_for::<T>(&self.name, table)
            .map_err(|issues| ContextError::Settings { file: self.config.source.clone(), issues })
    }

    /// Runtime options from the config's `[run]` table.
    pub fn runtime_options(&self) -> RuntimeOptions {
        RuntimeOptions {
            heartbeat_interval: Duration::from_secs_f64(self.config.run.heartbeat_interval_s),
            stats_interval: Duration::from_secs_f64(self.config.run.stats_interval_s),
            publish_control: true,
            final_stats_dir: Some(self.run_dir.join("stats")),
            extra_subscribers: self.config.run.extra_subscribers,
            remap: self.config.processes[&self.name].remap.clone(),
        }
    }

    /// Where this process writes its part of summary.json (merged by the supervisor).
    pub fn summary_part_path(&self) -> PathBuf {
        self.run_dir.join("parts").join(format!("{}.json", self.name))
    }
}

/// Environment variable through which the supervisor hands the run's output directory.
pub const ENV_OUT_DIR: &str = "SLAM_PIPELINE_OUT_DIR";

/// Options of a [`Runtime`].
#[derive(Debug, Clone)]
pub struct RuntimeOptions {
    /// Heartbeat period.
    pub heartbeat_interval: Duration,
    /// Statistics period.
    pub stats_interval: Duration,
    /// Publish heartbeats and statistics (false for the supervisor itself).
    pub publish_control: bool,
    /// Where the final statistics report is written at the end of [`Runtime::run`]
    /// (`<dir>/<process>-<pid>.bin`): a report published just before exit may never be read.
    pub final_stats_dir: Option<PathBuf>,
    /// The run's `run.extra_subscribers`: added to every service's `max_subscribers` and
    /// `max_nodes` where this runtime opens it ([`Qos::with_extra`]), as every process of the run
    /// must.
    pub extra_subscribers: usize,
    /// The process's `remap` table (`contract name -> name`): ports on a listed service open the
    /// other name, with the contract service's type and QoS ([`Runtime::service_name`]).
    pub remap: std::collections::BTreeMap<String, String>,
}

impl Default for RuntimeOptions {
    fn default() -> Self {
        Self {
            heartbeat_interval: Duration::from_millis(250),
            stats_interval: Duration::from_secs(1),
            publish_control: true,
            final_stats_dir: None,
            extra_subscribers: 0,
            remap: Default::default(),
        }
    }
}

/// What woke the loop.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Wake {
    /// At least one input was notified: drain the inputs.
    pub data: bool,
    /// The process's own tick (the `tick` given to [`Runtime::run`]) is due.
    pub tick: bool,
}

/// What the handler wants next.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Flow {
    /// Keep running.
    Continue,
    /// Leave the loop (e.g. after end of stream).
    Stop,
}

/// Why [`Runtime::run`] returned.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StopReason {
    /// The handler returned [`Flow::Stop`].
    Finished,
    /// SIGINT or SIGTERM (the signal number).
    Signal(i32),
}

/// One process's node, ports and loop.
pub struct Runtime {
    name: String,
    pid: u32,
    /// The iceoryx2 node (`None` for an in-process runtime).
    node: Option<Node<ipc::Service>>,
    /// The in-process services of a runtime under test (see [`crate::testing`]).
    bus: Option<Rc<LocalBus>>,
    started: Instant,
    pub(crate) options: RuntimeOptions,
    ports: Vec<Rc<RefCell<PortStats>>>,
    listeners: Vec<Rc<Listener<ipc::Service>>>,
    connectors: Vec<Rc<dyn Fn()>>,
    heartbeat: Option<Output<Heartbeat, MsgHeader>>,
    stats_out: Option<Output<[u8], MsgHeader>>,
    eos_out: Option<Output<EndOfStream, MsgHeader>>,
    signal: Arc<AtomicUsize>,
    /// Shared with the outputs' back-pressure handlers.
    backpressure: Arc<Backpressure>,
    /// Publishes heartbeats while a send waits for a full subscriber (started with the first
    /// waiting output).
    keep_alive: Option<KeepAlive>,
    scope: Option<IoxScope>,
    /// Messages in and out at the last heartbeat, for the keep-alive's heartbeats.
    counts: Arc<(std::sync::atomic::AtomicU64, std::sync::atomic::AtomicU64)>,
    state: u32,
    /// Upstream processes whose stream ended with `EOS_FAILED`.
    failed_upstream: RefCell<std::collections::BTreeSet<String>>,
    last_heartbeat: Option<Instant>,
    last_stats: Option<Instant>,
    /// The source's share of its input done ([`Runtime::set_progress`]).
    progress: Option<f64>,
    wake_at: Option<Instant>,
    /// The stage's restart state (disabled until [`crate::stage::run_stage`] opens it).
    restart_state: crate::restart::StateStore,
    /// Threads that turn [`Waker::wake`] calls into iceoryx2 events (joined on drop).
    /// The pending flags of the [`Waker`]s, cleared before each step.
    wakers: Vec<Arc<std::sync::atomic::AtomicBool>>,
}

/// While it lives, the process's heartbeat goes on from the keep-alive thread
/// ([`Runtime::hold_heartbeat`]).
#[must_use = "the heartbeat is held only while this lives"]
pub struct HeartbeatHold {
    bp: Arc<Backpressure>,
}

impl Drop for HeartbeatHold {
    fn drop(&mut self) {
        self.bp.end_external_wait();
    }
}

/// Wakes a process's loop from any thread (a network callback, a worker): [`Runtime::waker`].
/// Cheap to clone and to call; wakes that come while one is pending are merged.
#[derive(Clone)]
pub struct Waker {
    inner: Arc<WakeNotifier>,
}

/// The notifier behind a [`Waker`]: a port of the thread-safe iceoryx2 service variant (the same
/// shared-memory resources as `ipc`, its ports behind a mutex), so the waking thread notifies the
/// loop's listener itself, with no thread in between.
struct WakeNotifier {
    /// Set by the first wake after the loop last woke; cleared by the loop before its step.
    pending: Arc<std::sync::atomic::AtomicBool>,
    notifier: iceoryx2::port::notifier::Notifier<ipc_threadsafe::Service>,
    _node: Node<ipc_threadsafe::Service>,
}

impl std::fmt::Debug for Waker {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Waker").field("pending", &self.inner.pending.load(Ordering::Relaxed)).finish()
    }
}

impl Waker {
    /// Wakes the loop (the stage's next `step` sees `wake.data`); never blocks.
    pub fn wake(&self) {
        if !self.inner.pending.swap(true, Ordering::AcqRel)
            && let Err(e) = self.inner.notifier.notify()
        {
            self.inner.pending.store(false, Ordering::Release);
            tracing::warn!("waker: {e:?}");
        }
    }
}

/// The event service of a [`Waker`].
fn open_wake_event<S: iceoryx2::service::Service>(
    node: &Node<S>,
    name: &str,
) -> Result<iceoryx2::service::port_factory::event::PortFactory<S>, RuntimeError> {
    let svc_name = ServiceName::new(name).map_err(|_| RuntimeError::Port(PortError::InvalidName(name.to_string())))?;
    node.service_builder(&svc_name)
        .event()
        .max_notifiers(2)
        .max_listeners(1)
        .max_nodes(2)
        .open_or_create()
        .map_err(|e| RuntimeError::Port(PortError::Open { service: name.to_string(), reason: format!("{e:?}") }))
}

fn qos_of(service: &str) -> Result<Qos, RuntimeError> {
    services::service_spec(service).map(|s| s.qos).ok_or_else(|| RuntimeError::UnknownService(service.into()))
}

impl Runtime {
    /// Creates the node `name` in `scope` and installs SIGINT/SIGTERM handlers.
    pub fn new(name: &str, scope: &IoxScope, options: RuntimeOptions) -> Result<Self, RuntimeError> {
        let node = scope.create_node(name)?;
        let signal = Arc::new(AtomicUsize::new(0));
        let backpressure =
            Backpressure::new(scope.config()?, Arc::new(std::sync::atomic::AtomicBool::new(false)), signal.clone());
        for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
            signal_hook::flag::register_usize(sig, signal.clone(), sig as usize).map_err(RuntimeError::Signals)?;
        }
        let mut rt = Self {
            name: name.to_string(),
            pid: std::process::id(),
            node: Some(node),
            bus: None,
            started: Instant::now(),
            options,
            ports: vec![],
            listeners: vec![],
            wakers: vec![],
            connectors: vec![],
            heartbeat: None,
            stats_out: None,
            eos_out: None,
            signal,
            backpressure,
            keep_alive: None,
            scope: Some(scope.clone()),
            counts: Arc::new(Default::default()),
            state: shared_types::STATE_STARTING,
            failed_upstream: RefCell::default(),
            last_heartbeat: None,
            last_stats: None,
            progress: None,
            wake_at: None,
            restart_state: crate::restart::StateStore::disabled(),
        };
        if rt.options.publish_control {
            let hb_stats = Rc::new(RefCell::new(PortStats::new(services::HEARTBEAT, false)));
            let node = rt.node.as_ref().expect("created above");
            let extra = rt.options.extra_subscribers;
            rt.heartbeat = Some(Output::create(
                node,
                services::HEARTBEAT,
                &services::CONTROL_QOS.with_extra(extra),
                Delivery::DiscardWhenFull,
                hb_stats,
                rt.backpressure.clone(),
            )?);
            let st_stats = Rc::new(RefCell::new(PortStats::new("stats", false)));
            let stats_name = services::stats_service(name);
            rt.stats_out = Some(Output::create_slice(
                node,
                &stats_name,
                &services::STATS_QOS.with_extra(extra),
                st_stats,
                rt.backpressure.clone(),
            )?);
            rt.publish_heartbeat();
        }
        Ok(rt)
    }

    /// An in-process runtime for a stage under test: its ports are in-process queues (no
    /// iceoryx2, no shared memory, no signal handlers, no heartbeats); see [`crate::testing`].
    pub(crate) fn local(name: &str, bus: Rc<LocalBus>) -> Self {
        let signal = Arc::new(AtomicUsize::new(0));
        let backpressure = Backpressure::new(
            iceoryx2::config::Config::default(),
            Arc::new(std::sync::atomic::AtomicBool::new(false)),
            signal.clone(),
        );
        Self {
            name: name.to_string(),
            pid: std::process::id(),
            node: None,
            bus: Some(bus),
            started: Instant::now(),
            options: RuntimeOptions { publish_control: false, final_stats_dir: None, ..Default::default() },
            ports: vec![],
            listeners: vec![],
            wakers: vec![],
            connectors: vec![],
            heartbeat: None,
            stats_out: None,
            eos_out: None,
            signal,
            backpressure,
            keep_alive: None,
            scope: None,
            counts: Arc::new(Default::default()),
            state: shared_types::STATE_READY,
            failed_upstream: RefCell::default(),
            last_heartbeat: None,
            last_stats: None,
            progress: None,
            wake_at: None,
            restart_state: crate::restart::StateStore::disabled(),
        }
    }

    /// The stage's restart state: record journal lines and write snapshots here (see
    /// [`crate::restart`]); a restarted instance gets them back in [`crate::Stage::restore`].
    pub fn state(&mut self) -> &mut crate::restart::StateStore {
        &mut self.restart_state
    }

    pub(crate) fn set_state(&mut self, state: crate::restart::StateStore) {
        self.restart_state = state;
    }

    /// A restarted instance: where the killed one's inputs stopped (per service and publisher,
    /// the first sequence number it had not received or kept), so that the first later message
    /// counts what was lost from there ([`PortStats::note_seq`]).
    pub(crate) fn resume_inputs(&mut self, seqs: &[(String, u128, u64)]) {
        for port in self.ports.iter().filter(|p| p.borrow().input) {
            let mut st = port.borrow_mut();
            for (service, publisher, seq) in seqs {
                if *service == st.service {
                    st.resume_at.insert(*publisher, *seq);
                }
            }
            st.seq_dirty = !st.resume_at.is_empty();
        }
    }

    /// Writes where each input stands to the restart state when it changed (after a wake-up):
    /// per publisher the first sequence number not received or not kept (the stage's held
    /// messages are the newest publisher's newest); the publishers a restarted instance has not
    /// heard from again keep its predecessor's.
    pub(crate) fn save_inputs(&mut self) -> Result<(), crate::restart::StateError> {
        if !self.ports.iter().any(|p| p.borrow().seq_dirty) {
            return Ok(());
        }
        let mut seqs = vec![];
        for port in self.ports.iter() {
            let mut st = port.borrow_mut();
            st.seq_dirty = false;
            if !st.input || st.service == shared_types::services::END_OF_STREAM {
                continue;
            }
            for (publisher, next) in st.resume_at.iter().filter(|(p, _)| !st.last_seq.contains_key(p)) {
                seqs.push((st.service.clone(), *publisher, *next));
            }
            for (publisher, seq) in &st.last_seq {
                let held = if st.last_publisher == Some(*publisher) { st.held } else { 0 };
                seqs.push((st.service.clone(), *publisher, (seq + 1).saturating_sub(held)));
            }
        }
        self.restart_state.save_inputs(&seqs)
    }

    /// Takes the deadline set with [`Runtime::wake_at`] (for a test driving a stage).
    pub(crate) fn take_wake_at(&mut self) -> Option<Instant> {
        self.wake_at.take()
    }

    fn node_or_local(&self, service: &str) -> Result<&Node<ipc::Service>, Rc<LocalBus>> {
        match (&self.node, &self.bus) {
            (Some(node), _) => Ok(node),
            (None, Some(bus)) => Err(bus.clone()),
            (None, None) => unreachable!("a runtime has a node or an in-process bus ({service})"),
        }
    }

    /// For a process started by the supervisor: context, logging guard and runtime in one call.
    pub fn start(args: &ProcessArgs) -> Result<(ProcessContext, Self), StageError> {
        let ctx = ProcessContext::from_args(args)?;
        let rt = Runtime::new(&ctx.name, &ctx.scope, ctx.runtime_options())?;
        Ok((ctx, rt))
    }

    /// Process name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The iceoryx2 node (`None` for an in-process runtime under test).
    pub fn node(&self) -> Option<&Node<ipc::Service>> {
        self.node.as_ref()
    }

    /// Time since the runtime started.
    pub fn uptime(&self) -> Duration {
        self.started.elapsed()
    }

    /// The name this process opens `service` under: its `remap` entry, or `service` itself.
    pub fn service_name<'a>(&'a self, service: &'a str) -> &'a str {
        self.options.remap.get(service).map_or(service, String::as_str)
    }

    /// The inputs opened under a remapped name (`contract name -> name`).
    pub fn remapped_inputs(&self) -> Vec<(String, String)> {
        let names: std::collections::BTreeSet<String> =
            self.ports.iter().filter(|p| p.borrow().input).map(|p| p.borrow().service.clone()).collect();
        self.options.remap.iter().filter(|(_, to)| names.contains(*to)).map(|(f, t)| (f.clone(), t.clone())).collect()
    }

    fn port_stats(&mut self, service: &str, input: bool) -> Rc<RefCell<PortStats>> {
        let s = Rc::new(RefCell::new(PortStats::new(service, input)));
        self.ports.push(s.clone());
        s
    }

    /// Publisher of fixed-size values on a service of the contract.
    pub fn output<T: Debug + ZeroCopySend + Copy + 'static, H: Header>(
        &mut self,
        service: &str,
    ) -> Result<Output<T, H>, RuntimeError> {
        let qos = qos_of(service)?;
        self.output_with_qos(service, &qos, Delivery::DiscardWhenFull)
    }

    /// Publisher of fixed-size values with explicit QoS.
    pub fn output_with_qos<T: Debug + ZeroCopySend + Copy + 'static, H: Header>(
        &mut self,
        service: &str,
        qos: &Qos,
        delivery: Delivery,
    ) -> Result<Output<T, H>, RuntimeError> {
        let service = &self.service_name(service).to_string();
        let stats = self.port_stats(service, false);
        self.keep_alive_for(delivery);
        let qos = &qos.with_extra(self.options.extra_subscribers);
        match self.node_or_local(service) {
            Ok(node) => Ok(Output::create(node, service, qos, delivery, stats, self.backpressure.clone())?),
            Err(bus) => Ok(Output::local(service, bus.queue(service, Side::Output)?, stats)),
        }
    }

    /// Publisher of slices on a service of the contract, reserving `initial_len` elements.
    pub fn output_slice<T: Debug + ZeroCopySend + Copy + 'static, H: Header>(
        &mut self,
        service: &str,
        initial_len: usize,
    ) -> Result<Output<[T], H>, RuntimeError> {
        let qos = qos_of(service)?;
        self.output_slice_with_qos(service, &qos, initial_len, Delivery::DiscardWhenFull)
    }

    /// Publisher of slices with explicit QoS.
    pub fn output_slice_with_qos<T: Debug + ZeroCopySend + Copy + 'static, H: Header>(
        &mut self,
        service: &str,
        qos: &Qos,
        initial_len: usize,
        delivery: Delivery,
    ) -> Result<Output<[T], H>, RuntimeError> {
        let service = &self.service_name(service).to_string();
        let stats = self.port_stats(service, false);
        self.keep_alive_for(delivery);
        let qos = &qos.with_extra(self.options.extra_subscribers);
        match self.node_or_local(service) {
            Ok(node) => Ok(Output::create_slice_with_len(
                node,
                service,
                qos,
                initial_len,
                delivery,
                stats,
                self.backpressure.clone(),
            )?),
            Err(bus) => Ok(Output::local(service, bus.queue(service, Side::Output)?, stats)),
        }
    }

    /// Subscriber on a service of the contract (`P` = `T` or `[T]`); the loop wakes on its events.
    pub fn input<P: crate::ports::Payload + ?Sized, H: Header>(
        &mut self,
        service: &str,
    ) -> Result<Input<P, H>, RuntimeError> {
        let qos = qos_of(service)?;
        self.input_with_qos(service, &qos)
    }

    /// Subscriber with explicit QoS.
    pub fn input_with_qos<P: crate::ports::Payload + ?Sized, H: Header>(
        &mut self,
        service: &str,
        qos: &Qos,
    ) -> Result<Input<P, H>, RuntimeError> {
        self.input_with_buffer_qos(service, qos, qos.subscriber_buffer)
    }

    /// Subscriber on a service of the contract that holds at most `buffer` samples (1 up to the
    /// service's subscriber buffer): a replaying source that waits for its subscribers is then at
    /// most `buffer` messages ahead of this one (its latency through the queue stays short),
    /// and a live source drops (counted) when this process falls `buffer` messages behind.
    pub fn input_with_buffer<P: crate::ports::Payload + ?Sized, H: Header>(
        &mut self,
        service: &str,
        buffer: usize,
    ) -> Result<Input<P, H>, RuntimeError> {
        let qos = qos_of(service)?;
        self.input_with_buffer_qos(service, &qos, buffer)
    }

    fn input_with_buffer_qos<P: crate::ports::Payload + ?Sized, H: Header>(
        &mut self,
        service: &str,
        qos: &Qos,
        buffer: usize,
    ) -> Result<Input<P, H>, RuntimeError> {
        let service = &self.service_name(service).to_string();
        let stats = self.port_stats(service, true);
        let qos = &qos.with_extra(self.options.extra_subscribers);
        let input = match self.node_or_local(service) {
            Ok(node) => Input::create(node, service, qos, buffer, stats)?,
            Err(bus) => Input::local(service, bus.queue(service, Side::Input)?, stats),
        };
        self.listeners.extend(input.listener());
        self.connectors.extend(input.connector());
        Ok(input)
    }

    /// Announces that this process has sent its last data message (`last_seq`, `messages_sent`).
    pub fn send_end_of_stream(&mut self, last_seq: u64, messages_sent: u64) -> Result<(), RuntimeError> {
        if self.eos_out.is_none() {
            self.eos_out = Some(self.output_with_qos(
                services::END_OF_STREAM,
                &services::CONTROL_QOS,
                Delivery::DiscardWhenFull,
            )?);
        }
        let eos = EndOfStream {
            process: name32(&self.name),
            last_seq,
            messages_sent,
            status: shared_types::EOS_COMPLETE,
            outputs: shared_types::EOS_OUTPUTS_KNOWN | self.data_service_bits(false),
        };
        let now = monotonic_ns();
        let header = MsgHeader { stamp_ns: now, origin_ns: now, ..Default::default() };
        self.eos_out.as_mut().expect("created above").send_value(header, eos)?;
        tracing::info!(last_seq, messages_sent, "sent end of stream");
        Ok(())
    }

    /// Drains an end-of-stream input and returns the names of the *other* processes that ended.
    /// Call it before draining the data inputs in the same wake-up: everything those processes
    /// sent before their end of stream is then already queued, so the data drain that follows
    /// misses nothing (read the other way round, a last message can slip in between).
    ///
    /// A process the supervisor gave up on ends too (`EOS_FAILED`, sent in its name): it is
    /// returned like the others, so that its consumers finish with what they have, and is warned
    /// about and listed in [`Runtime::failed_upstream`].
    pub fn ended_upstream(&self, eos: &Input<EndOfStream, MsgHeader>) -> Result<Vec<String>, PortError> {
        Ok(self.ends_upstream(eos)?.into_iter().map(|(name, _)| name).collect())
    }

    /// As [`Runtime::ended_upstream`], with each process's `EndOfStream::outputs` (the data
    /// services it published; see [`Runtime::feeds_inputs`]).
    pub fn ends_upstream(&self, eos: &Input<EndOfStream, MsgHeader>) -> Result<Vec<(String, u32)>, PortError> {
        let mut ended = vec![];
        while let Some(s) = eos.receive()? {
            let from = shared_types::name_from32(&s.payload().process);
            if from != self.name {
                if s.payload().status == shared_types::EOS_FAILED
                    && self.failed_upstream.borrow_mut().insert(from.clone())
                {
                    tracing::warn!(
                        upstream = %from,
                        "`{from}` failed for good: its stream ends here (the supervisor says so); \
                         finishing with what it sent"
                    );
                }
                ended.push((from, s.payload().outputs));
            }
        }
        Ok(ended)
    }

    /// The `EndOfStream::outputs` bits of the data services this process opened as inputs
    /// (`input`) or outputs.
    pub fn data_service_bits(&self, input: bool) -> u32 {
        self.ports
            .iter()
            .filter(|p| p.borrow().input == input)
            .filter_map(|p| shared_types::services::data_service_bit(&p.borrow().service))
            .fold(0, |a, b| a | b)
    }

    /// Whether a process that ended with `outputs` (`EndOfStream::outputs`) fed this process:
    /// it published one of this process's inputs, or did not say what it published.
    pub fn feeds_inputs(&self, outputs: u32) -> bool {
        outputs & shared_types::EOS_OUTPUTS_KNOWN == 0 || outputs & self.data_service_bits(true) != 0
    }

    /// The processes whose stream ended because they failed for good (`EOS_FAILED`), as seen by
    /// [`Runtime::ended_upstream`].
    pub fn failed_upstream(&self) -> Vec<String> {
        self.failed_upstream.borrow().iter().cloned().collect()
    }

    /// A [`Waker`] for work that arrives outside iceoryx2 (a network callback, another thread):
    /// its `wake` makes the loop's WaitSet return (no polling). The event travels on the
    /// private service `pipeline/wake/<process>/<pid>/<n>` through a thread with its own node,
    /// stopped and joined when the runtime is dropped. Needs shared memory (not in-process).
    pub fn waker(&mut self) -> Result<Waker, RuntimeError> {
        let (Some(node), Some(scope)) = (&self.node, &self.scope) else { return Err(RuntimeError::Local) };
        let name = format!("pipeline/wake/{}/{}/{}", self.name, self.pid, self.wakers.len());
        let svc = open_wake_event(node, &name)?;
        let listener = svc
            .listener_builder()
            .create()
            .map_err(|e| RuntimeError::Port(PortError::Open { service: name.clone(), reason: format!("{e:?}") }))?;
        self.listeners.push(Rc::new(listener));
        let open = |e: String| RuntimeError::Port(PortError::Open { service: name.clone(), reason: e });
        let node = scope
            .create_threadsafe_node(&format!("{}.waker{}", self.name, self.wakers.len()))
            .map_err(|e| open(e.to_string()))?;
        let notifier =
            open_wake_event(&node, &name)?.notifier_builder().create().map_err(|e| open(format!("{e:?}")))?;
        let pending = Arc::new(std::sync::atomic::AtomicBool::new(false));
        self.wakers.push(pending.clone());
        Ok(Waker { inner: Arc::new(WakeNotifier { pending, notifier, _node: node }) })
    }

    /// Asks for a `wake.tick` at `at` (earlier than the regular tick, if need be): for sources that
    /// publish on a data clock. The loop sleeps until then unless data or a signal arrives.
    pub fn wake_at(&mut self, at: Instant) {
        self.wake_at = Some(self.wake_at.map_or(at, |w| w.min(at)));
    }

    /// The termination signal received so far, if any.
    pub fn termination_signal(&self) -> Option<i32> {
        match self.signal.load(Ordering::Relaxed) {
            0 => None,
            s => Some(s as i32),
        }
    }

    /// Starts the keep-alive thread with the first output that may wait for its subscribers.
    fn keep_alive_for(&mut self, delivery: Delivery) {
        if matches!(delivery, Delivery::WaitWhenFull { .. })
            && self.keep_alive.is_none()
            && self.options.publish_control
            && let Some(scope) = &self.scope
        {
            self.keep_alive = Some(KeepAlive::spawn(
                scope.clone(),
                self.name.clone(),
                self.pid,
                &self.options,
                self.backpressure.clone(),
                self.counts.clone(),
                self.started,
            ));
        }
    }

    /// Keeps the process's heartbeat going (from the keep-alive thread) while the stage blocks
    /// outside iceoryx2, until the returned hold is dropped: e.g. a network send held back by a
    /// slow link, which is waiting for a slow consumer, not a hang.
    pub fn hold_heartbeat(&mut self) -> HeartbeatHold {
        self.keep_alive_for(Delivery::WaitWhenFull { max_wait: None });
        self.backpressure.begin_external_wait();
        HeartbeatHold { bp: self.backpressure.clone() }
    }

    /// Total time this process's sends waited for full subscribers (back-pressure).
    pub fn backpressure_waited(&self) -> Duration {
        self.backpressure.waited()
    }

    fn publish_heartbeat(&mut self) {
        let (messages_in, messages_out) = self.ports.iter().fold((0, 0), |(i, o), p| {
            let p = p.borrow();
            if p.input { (i + p.count, o) } else { (i, o + p.count) }
        });
        self.counts.0.store(messages_in, Ordering::Relaxed);
        self.counts.1.store(messages_out, Ordering::Relaxed);
        let Some(out) = self.heartbeat.as_mut() else { return };
        let hb = Heartbeat {
            process: name32(&self.name),
            pid: self.pid,
            state: self.state,
            uptime_ns: self.started.elapsed().as_nanos() as u64,
            messages_in,
            messages_out,
        };
        let now = monotonic_ns();
        if let Err(e) = out.send_value(MsgHeader { stamp_ns: now, origin_ns: now, ..Default::default() }, hb) {
            tracing::warn!("heartbeat not sent: {e}");
        }
        self.last_heartbeat = Some(Instant::now());
    }

    /// Publishes a heartbeat now if one is due: for a handler that does long work in one go
    /// (writing a large map at the end), between its steps, so that the supervisor's heartbeat
    /// deadline does not take it for hung.
    pub fn keep_alive(&mut self) {
        let interval = self.options.heartbeat_interval;
        if self.last_heartbeat.is_none_or(|t| t.elapsed() >= interval) {
            self.publish_heartbeat();
        }
    }

    /// Builds this process's statistics report (cumulative since start).
    pub fn stats_report(&self) -> StatsReport {
        let borrowed: Vec<_> = self.ports.iter().map(|p| p.borrow()).collect();
        let mut report = StatsReport::from_ports(
            &self.name,
            self.pid,
            self.started.elapsed().as_nanos() as u64,
            borrowed.iter().map(|b| &**b),
        );
        report.progress = self.progress;
        report
    }

    /// Tells the supervisor how much of its input this process has done (0 to 1: a replay's share
    /// of its data time, a simulation's share of its mission), in the next statistics report. The
    /// supervisor's live view draws the run's progress bar and its ETA from it. Values outside
    /// [0, 1] are clamped; a NaN is ignored.
    pub fn set_progress(&mut self, fraction: f64) {
        if !fraction.is_nan() {
            self.progress = Some(fraction.clamp(0.0, 1.0));
        }
    }

    fn publish_stats(&mut self) {
        self.last_stats = Some(Instant::now());
        if self.stats_out.is_none() {
            return;
        }
        let bytes = match self.stats_report().encode() {
            Ok(b) => b,
            Err(e) => {
                tracing::warn!("statistics not encoded: {e}");
                return;
            }
        };
        let out = self.stats_out.as_mut().expect("checked above");
        let result = out.loan_slice_uninit(bytes.len()).and_then(|s| {
            let mut s = s.write_from_slice(&bytes);
            let now = monotonic_ns();
            *s.user_header_mut() = MsgHeader { stamp_ns: now, origin_ns: now, ..Default::default() };
            out.send(s)
        });
        if let Err(e) = result {
            tracing::warn!("statistics not sent: {e}");
        }
    }

    fn periodic(&mut self, now: Instant) {
        if !self.options.publish_control {
            return;
        }
        if self.last_heartbeat.is_none_or(|t| now - t >= self.options.heartbeat_interval) {
            self.publish_heartbeat();
        }
        if self.last_stats.is_none_or(|t| now - t >= self.options.stats_interval) {
            self.publish_stats();
        }
    }

    /// Runs the loop: blocks in a WaitSet on every input's events and an interval tick, calls
    /// `handler` when an input was notified (`wake.data`) or the process's own `tick` is due
    /// (`wake.tick`), and returns when the handler says [`Flow::Stop`] or on SIGINT/SIGTERM.
    /// The first heartbeat with state READY goes out on entry: that is "ready" for the supervisor.
    pub fn run<S, E: From<RuntimeError>>(
        &mut self,
        state: &mut S,
        tick: Option<Duration>,
        mut handler: impl FnMut(&mut Runtime, &mut S, Wake) -> Result<Flow, E>,
    ) -> Result<StopReason, E> {
        if self.node.is_none() {
            return Err(RuntimeError::Local.into());
        }
        let listeners = self.listeners.clone();
        let ws = WaitSetBuilder::new()
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .map_err(|e| RuntimeError::WaitSet(format!("{e:?}")))?;
        let guards = listeners
            .iter()
            .map(|l| ws.attach_notification(l.as_ref()))
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| RuntimeError::WaitSet(format!("attach: {e:?}")))?;
        let mut period = tick.unwrap_or(Duration::from_secs(3600));
        if self.options.publish_control {
            period = period.min(self.options.heartbeat_interval).min(self.options.stats_interval);
        }
        let timer = ws.attach_interval(period).map_err(|e| RuntimeError::WaitSet(format!("interval: {e:?}")))?;

        self.state = shared_types::STATE_READY;
        self.publish_heartbeat();
        tracing::info!(inputs = listeners.len(), "ready");
        let mut next_tick = tick.map(|t| Instant::now() + t);
        let reason = loop {
            if let Some(sig) = self.termination_signal() {
                break StopReason::Signal(sig);
            }
            let mut wake = Wake::default();
            ws.wait_and_process_once_with_timeout(
                |id| {
                    for (listener, guard) in listeners.iter().zip(&guards) {
                        if id.has_event_from(guard) {
                            // Drain the listener, or the WaitSet wakes again at once.
                            let _ = listener.try_wait(|_| {});
                            wake.data = true;
                        }
                    }
                    let _ = id.has_event_from(&timer);
                    CallbackProgression::Continue
                },
                self.wake_at.map_or(period, |w| w.saturating_duration_since(Instant::now()).min(period)),
            )
            .map_err(|e| RuntimeError::WaitSet(format!("wait: {e:?}")))?;
            // After the listeners were drained and before the step: a wake from now on notifies
            // again (one before this is seen by the step anyway).
            for pending in &self.wakers {
                pending.store(false, Ordering::Release);
            }
            for connect in &self.connectors {
                connect();
            }
            let now = Instant::now();
            if let (Some(t), Some(due)) = (tick, next_tick)
                && now >= due
            {
                wake.tick = true;
                next_tick = Some(if now - due > t { now + t } else { due + t });
            }
            if self.wake_at.is_some_and(|w| now >= w) {
                self.wake_at = None;
                wake.tick = true;
            }
            self.periodic(now);
            if (wake.data || wake.tick) && handler(self, state, wake)? == Flow::Stop {
                break StopReason::Finished;
            }
        };
        self.state = shared_types::STATE_STOPPING;
        if self.options.publish_control {
            self.publish_stats();
            self.publish_heartbeat();
        }
        if let Some(dir) = &self.options.final_stats_dir {
            let path = dir.join(format!("{}-{}.bin", self.name, self.pid));
            let written = std::fs::create_dir_all(dir)
                .map_err(|e| e.to_string())
                .and_then(|_| self.stats_report().encode().map_err(|e| e.to_string()))
                .and_then(|b| std::fs::write(&path, b).map_err(|e| e.to_string()));
            if let Err(e) = written {
                tracing::warn!("final statistics not written to {}: {e}", path.display());
            }
        }
        tracing::info!(?reason, "stopping");
        Ok(reason)
    }
}

/// A thread that publishes the process's heartbeat while one of its sends waits for a full
/// subscriber (the loop is blocked inside `send` then): waiting for a slow consumer is not a
/// hang. It has its own iceoryx2 node (`<process>.keepalive`) and stops with the runtime.
struct KeepAlive {
    stop: Arc<std::sync::atomic::AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl KeepAlive {
    fn spawn(
        scope: IoxScope,
        name: String,
        pid: u32,
        options: &RuntimeOptions,
        bp: Arc<Backpressure>,
        counts: Arc<(std::sync::atomic::AtomicU64, std::sync::atomic::AtomicU64)>,
        started: Instant,
    ) -> Self {
        let (interval, control_qos) =
            (options.heartbeat_interval, services::CONTROL_QOS.with_extra(options.extra_subscribers));
        let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let stop_t = stop.clone();
        let thread = std::thread::Builder::new()
            .name("keep-alive".into())
            .spawn(move || {
                let setup = || -> Result<_, RuntimeError> {
                    let node = scope.create_node(&format!("{name}.keepalive"))?;
                    let hb_stats = Rc::new(RefCell::new(PortStats::new(services::HEARTBEAT, false)));
                    let out = Output::<Heartbeat, MsgHeader>::create(
                        &node,
                        services::HEARTBEAT,
                        &control_qos,
                        Delivery::DiscardWhenFull,
                        hb_stats,
                        bp.clone(),
                    )?;
                    Ok((node, out))
                };
                let (_node, mut out) = match setup() {
                    Ok(x) => x,
                    Err(e) => {
                        tracing::warn!("keep-alive heartbeats unavailable: {e}");
                        return;
                    }
                };
                while !stop_t.load(Ordering::Relaxed) {
                    std::thread::sleep(interval / 2);
                    if !bp.is_waiting() {
                        continue;
                    }
                    let hb = Heartbeat {
                        process: name32(&name),
                        pid,
                        state: shared_types::STATE_READY,
                        uptime_ns: started.elapsed().as_nanos() as u64,
                        messages_in: counts.0.load(Ordering::Relaxed),
                        messages_out: counts.1.load(Ordering::Relaxed),
                    };
                    let now = monotonic_ns();
                    let _ = out.send_value(MsgHeader { stamp_ns: now, origin_ns: now, ..Default::default() }, hb);
                }
            })
            .ok();
        Self { stop, thread }
    }
}

impl Drop for KeepAlive {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}
