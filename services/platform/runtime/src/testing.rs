//! Unit tests of a [`Stage`] without iceoryx2: [`StageHarness`] opens the stage on an in-process
//! runtime whose ports are queues, feeds its inputs, wakes it the way the loop would, and hands
//! back what it published, its end of stream and its summary part. The stage's code is the
//! same as in the process (its `open`, `step` and `finish`, and the runtime's end-of-stream
//! bookkeeping, [`EndAfter`](crate::stage::EndAfter)); only the transport differs.
//!
//! ```no_run
//! # use pipeline_runtime::testing::StageHarness;
//! # use pipeline_runtime::Stage;
//! # fn demo<S: Stage>() -> Result<(), pipeline_runtime::testing::TestError> {
//! let out = tempfile_dir();
//! let mut h = StageHarness::<S>::from_config_file("config/default.toml".as_ref(), "synchronizer", &out)?;
//! // h.feed(SLAM_POSE, MsgHeader { stamp_ns, ..Default::default() }, pose);
//! h.end_upstream("fastslam");
//! let part = h.run_to_end(std::time::Duration::from_secs(5))?; // the summary part
//! // let pairs = h.take::<SyncedPair, MsgHeader>(SYNC_PAIR);
//! # Ok(()) }
//! # fn tempfile_dir() -> std::path::PathBuf { unimplemented!() }
//! ```

use std::cell::RefCell;
use std::fmt::Debug;
use std::path::{Path, PathBuf};
use std::rc::Rc;
use std::time::{Duration, Instant};

use iceoryx2::prelude::ZeroCopySend;
use shared_types::services::END_OF_STREAM;
use shared_types::{EOS_COMPLETE, EOS_FAILED, EndOfStream, MsgHeader, name32};

use crate::clock::monotonic_ns;
use crate::config::{ConfigError, LogFormat, PipelineConfig, parse_toml_str};
use crate::error::{ContextError, StageError};
use crate::iox::IoxScope;
use crate::ports::{Header, LocalBus, PortError, Side};

use crate::runtime::{ProcessContext, Runtime, Wake};
use crate::stage::{Driver, Stage, Step};

/// What a [`StageHarness`] can fail with.
#[derive(Debug, thiserror::Error)]
pub enum TestError {
    /// The stage (or the runtime around it) failed.
    #[error(transparent)]
    Stage(#[from] StageError),
    /// The config text.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The config's process table or settings.
    #[error(transparent)]
    Context(#[from] ContextError),
    /// A queue used with another type than the stage's port.
    #[error(transparent)]
    Port(#[from] PortError),
    /// The config file cannot be read.
    #[error("{}: {source}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// The error.
        source: std::io::Error,
    },
    /// A message fed to a service the stage has no input on.
    #[error("`{stage}` has no input on `{service}`")]
    NoInput {
        /// The stage's process name.
        stage: String,
        /// The service.
        service: String,
    },
    /// [`StageHarness::run_to_end`] ran out of time.
    #[error("`{stage}` has not finished within {limit:?}")]
    NotFinished {
        /// The stage's process name.
        stage: String,
        /// The limit.
        limit: Duration,
    },
}

/// A stage opened on in-process queues (see the module docs).
pub struct StageHarness<S: Stage> {
    ctx: ProcessContext,
    bus: Rc<LocalBus>,
    rt: Runtime,
    stage: S,
    driver: Driver,
    /// Sequence numbers of the fed services.
    seqs: RefCell<std::collections::HashMap<String, u64>>,
}

impl<S: Stage> StageHarness<S> {
    /// Opens process `name` of the pipeline config in `path` (its settings validated as the
    /// process would), writing its outputs to `out_dir`.
    pub fn from_config_file(path: &Path, name: &str, out_dir: &Path) -> Result<Self, TestError> {
        let text = std::fs::read_to_string(path).map_err(|source| TestError::Read { path: path.into(), source })?;
        Self::from_config_str(&text, path, name, out_dir)
    }

    /// As [`StageHarness::from_config_file`] with the config's text (`source` names it in
    /// errors and resolves its relative paths as the file would).
    pub fn from_config_str(text: &str, source: &Path, name: &str, out_dir: &Path) -> Result<Self, TestError> {
        let mut config: PipelineConfig = parse_toml_str(text, source)?;
        config.source = source.to_path_buf();
        if !config.processes.contains_key(name) {
            return Err(ContextError::NoProcess { file: source.into(), name: name.into() }.into());
        }
        let ctx = ProcessContext {
            name: name.to_string(),
            scope: IoxScope { prefix: "local".into(), root: PathBuf::new(), base_config: None },
            out_dir: match &config.processes[name].out_dir {
                Some(own) => out_dir.join(own),
                None => out_dir.to_path_buf(),
            },
            run_dir: out_dir.to_path_buf(),
            config,
            log_format: LogFormat::Text,
        };
        let settings: S::Settings = ctx.settings()?;
        Self::open(ctx, settings)
    }

    /// Opens the stage with explicit settings (a first instance: its restart state starts
    /// empty under `<out>/state/<name>/`).
    pub fn open(ctx: ProcessContext, settings: S::Settings) -> Result<Self, TestError> {
        Self::open_instance(ctx, settings, false)
    }

    fn open_instance(ctx: ProcessContext, settings: S::Settings, restart: bool) -> Result<Self, TestError> {
        let bus = Rc::new(LocalBus::default());
        let mut rt = Runtime::local(&ctx.name, bus.clone());
        rt.options.remap = ctx.config.processes[&ctx.name].remap.clone();
        let mut stage = S::open(&ctx, settings, &mut rt)?;
        let driver = Driver::new(&ctx, &mut rt, &mut stage, restart)?;
        Ok(Self { ctx, bus, rt, stage, driver, seqs: Default::default() })
    }

    /// Kills this instance (nothing more is written; what its inputs held is lost, and the
    /// restarted instance counts it as [`crate::stats::LOST_IN_RESTART`] when the next message
    /// comes) and starts a restarted one, as the supervisor would: a new stage with the settings
    /// of the context's config, given the restart state the killed one kept
    /// ([`Stage::restore`]). The test's publishers go on numbering where they were.
    pub fn restart(self) -> Result<Self, TestError> {
        let ctx = self.ctx.clone();
        // The publishers go on: their sequence numbers continue after the restart.
        let seqs = self.seqs.take();
        drop(self);
        let settings: S::Settings = ctx.settings()?;
        let h = Self::open_instance(ctx, settings, true)?;
        *h.seqs.borrow_mut() = seqs;
        Ok(h)
    }

    /// The process context the stage was opened with.
    pub fn context(&self) -> &ProcessContext {
        &self.ctx
    }

    /// The stage (to look at its state).
    pub fn stage(&self) -> &S {
        &self.stage
    }

    /// The in-process runtime (e.g. for its statistics report).
    pub fn runtime(&self) -> &Runtime {
        &self.rt
    }

    fn stamp<H: Header>(&self, service: &str, mut header: H) -> H {
        let mut seqs = self.seqs.borrow_mut();
        let seq = seqs.entry(service.to_string()).or_default();
        let h = header.msg_mut();
        h.seq = *seq;
        *seq += 1;
        h.publish_ns = monotonic_ns();
        if h.origin_ns == 0 {
            h.origin_ns = h.publish_ns;
        }
        header
    }

    /// Skips `n` sequence numbers of `service`, as if a publisher had sent `n` messages that
    /// never reached the stage (lost in a full queue, or sent before it connected).
    pub fn lose(&self, service: &str, n: u64) {
        *self.seqs.borrow_mut().entry(service.to_string()).or_default() += n;
    }

    /// Queues a fixed-size message for every input of the stage on `service` (`seq`,
    /// `publish_ns` and a zero `origin_ns` are stamped as a publisher would). An error when the
    /// stage has no input on `service`, or one of another type.
    pub fn feed<T: Debug + ZeroCopySend + Copy + 'static, H: Header + Copy>(
        &self,
        service: &str,
        header: H,
        value: T,
    ) -> Result<(), TestError> {
        let header = self.stamp(service, header);
        let queues = self.bus.inputs::<T, H>(service)?;
        if queues.is_empty() {
            return Err(TestError::NoInput { stage: self.ctx.name.clone(), service: service.into() });
        }
        for q in queues {
            q.borrow_mut().push_back((header, Box::new(value)));
        }
        Ok(())
    }

    /// Queues a slice message for every input of the stage on `service`.
    pub fn feed_slice<T: Debug + ZeroCopySend + Copy + 'static, H: Header + Copy>(
        &self,
        service: &str,
        header: H,
        values: &[T],
    ) -> Result<(), TestError> {
        let header = self.stamp(service, header);
        let queues = self.bus.inputs::<[T], H>(service)?;
        if queues.is_empty() {
            return Err(TestError::NoInput { stage: self.ctx.name.clone(), service: service.into() });
        }
        for q in queues {
            q.borrow_mut().push_back((header, values.into()));
        }
        Ok(())
    }

    fn end_of(&self, process: &str, status: u32, outputs: u32) -> Result<(), TestError> {
        let eos = EndOfStream { process: name32(process), last_seq: 0, messages_sent: 0, status, outputs };
        self.feed(END_OF_STREAM, MsgHeader::default(), eos)
    }

    /// Queues the end of stream of process `process` (it completed) that says it published
    /// `services` (`EndOfStream::outputs`; [`StageHarness::end_upstream`] says nothing, so the
    /// stage takes it for an upstream whatever it subscribes to).
    pub fn end_of_process_publishing(&self, process: &str, services: &[&str]) -> Result<(), TestError> {
        let outputs = services
            .iter()
            .filter_map(|s| shared_types::services::data_service_bit(s))
            .fold(shared_types::EOS_OUTPUTS_KNOWN, |a, b| a | b);
        self.end_of(process, EOS_COMPLETE, outputs)
    }

    /// Queues the end of stream of upstream process `process` (it completed).
    pub fn end_upstream(&self, process: &str) -> Result<(), TestError> {
        self.end_of(process, EOS_COMPLETE, 0)
    }

    /// Queues the end of stream the supervisor sends for `process` when it gave up on it.
    pub fn fail_upstream(&self, process: &str) -> Result<(), TestError> {
        self.end_of(process, EOS_FAILED, 0)
    }

    /// One wake-up with data (as when an input was notified); `None` once the stage finished.
    pub fn wake(&mut self) -> Result<Option<Step>, TestError> {
        Ok(self.driver.wake(&mut self.rt, &mut self.stage, Wake { data: true, tick: false })?)
    }

    /// One wake-up of the stage's tick.
    pub fn tick(&mut self) -> Result<Option<Step>, TestError> {
        Ok(self.driver.wake(&mut self.rt, &mut self.stage, Wake { data: false, tick: true })?)
    }

    /// Wakes the stage until it has finished (its inputs ended, or a source's `Done`), sleeping
    /// until the deadlines it sets ([`Runtime::wake_at`]) as the loop would; returns its summary
    /// part. An error when it has not finished within `limit`.
    pub fn run_to_end(&mut self, limit: Duration) -> Result<serde_json::Value, TestError> {
        let started = Instant::now();
        let mut data = true;
        while !self.driver.done() {
            if started.elapsed() >= limit {
                return Err(TestError::NotFinished { stage: self.ctx.name.clone(), limit });
            }
            let wake = Wake { data, tick: !data };
            data = false;
            match self.driver.wake(&mut self.rt, &mut self.stage, wake)? {
                None | Some(Step::Done) => {}
                Some(Step::Busy) | Some(Step::Idle) => {
                    self.rt.take_wake_at();
                }
                Some(Step::Pending) => {
                    let until = self.rt.take_wake_at().unwrap_or_else(|| Instant::now() + Duration::from_millis(10));
                    std::thread::sleep(until.saturating_duration_since(Instant::now()).min(limit));
                }
            }
        }
        Ok(self.summary().cloned().unwrap_or_default())
    }

    /// Stops the stage as a SIGTERM would (its finish with `Ending::Stopped`, unless it has
    /// finished already); returns its summary part.
    pub fn stop(&mut self) -> Result<serde_json::Value, TestError> {
        self.driver.stop(&mut self.rt, &mut self.stage)?;
        Ok(self.summary().cloned().unwrap_or_default())
    }

    /// The summary part, once the stage has finished (also written to `<out>/parts/<name>.json`).
    pub fn summary(&self) -> Option<&serde_json::Value> {
        self.driver.part.as_ref()
    }

    /// Takes what the stage has published on `service` (fixed-size messages) so far.
    pub fn take<T: Debug + ZeroCopySend + Copy + 'static, H: Header>(
        &self,
        service: &str,
    ) -> Result<Vec<(H, T)>, TestError> {
        let q = self.bus.queue::<T, H>(service, Side::Output)?;
        let taken = q.borrow_mut().drain(..).map(|(h, p)| (h, *p)).collect();
        Ok(taken)
    }

    /// Takes what the stage has published on `service` (slice messages) so far.
    pub fn take_slices<T: Debug + ZeroCopySend + Copy + 'static, H: Header>(
        &self,
        service: &str,
    ) -> Result<Vec<(H, Vec<T>)>, TestError> {
        let q = self.bus.queue::<[T], H>(service, Side::Output)?;
        let taken = q.borrow_mut().drain(..).map(|(h, p)| (h, p.into_vec())).collect();
        Ok(taken)
    }

    /// The stage's own end of stream, once it has sent it.
    pub fn end_of_stream(&self) -> Result<Option<EndOfStream>, TestError> {
        Ok(self.take::<EndOfStream, MsgHeader>(END_OF_STREAM)?.pop().map(|(_, e)| e))
    }
}
