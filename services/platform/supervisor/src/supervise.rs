//! The supervision loop: start processes in dependency order once their dependencies report ready,
//! watch them (exit via waitpid, liveness via heartbeat deadline), restart per policy with
//! exponential backoff, clean a dead node's iceoryx2 resources after every exit, end the run
//! (duration, end of stream, signal), stop everything in reverse order and report.
//!
//! The loop blocks in the runtime's WaitSet on heartbeat, end-of-stream and stats events plus a
//! 50 ms tick (for waitpid and deadlines): it never spins.

use std::collections::{BTreeMap, BTreeSet};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use nix::sys::signal::{Signal, kill};
use nix::sys::wait::{WaitPidFlag, WaitStatus, waitpid};
use nix::unistd::Pid;
use pipeline_runtime::config::{EndCondition, RestartPolicy};
use pipeline_runtime::ports::Input;
use pipeline_runtime::runtime::ENV_OUT_DIR;
use pipeline_runtime::{Flow, Runtime, RuntimeOptions, StatsReport, StopReason};
use shared_types::services::{self, CONTROL_QOS, STATS_QOS};
use shared_types::{EndOfStream, Heartbeat, MsgHeader, STATE_READY, name_from32};

use crate::outcome::{EndReason, ExitInfo, Usage};
use crate::outcome::{rss_mib, wait_with_usage};
use crate::plan::{Plan, PlannedProcess};

/// Environment variable with the process's own name, for external processes.
pub const ENV_PROCESS_NAME: &str = "SLAM_PIPELINE_PROCESS";

/// Environment variable with the number of times the process was restarted before this instance
/// (0 for the first): a stage that keeps state under the output directory resumes from it only
/// when this is > 0, so a new run never picks up what an earlier run left there.
pub use pipeline_runtime::restart::ENV_RESTARTS;

const TICK: Duration = Duration::from_millis(50);

/// State of one supervised process.
#[derive(Debug, Clone, PartialEq)]
pub enum ProcState {
    /// Waiting for its dependencies.
    Pending,
    /// Spawned, not yet ready.
    Starting {
        /// When it was spawned.
        since: Instant,
    },
    /// Ready and running.
    Ready,
    /// Waiting to be restarted.
    Backoff {
        /// When it restarts.
        until: Instant,
    },
    /// Being stopped.
    Stopping,
    /// Ended and not restarted (a clean exit, or stopped by the supervisor).
    Done,
    /// Given up on.
    Failed(String),
}

impl ProcState {
    fn label(&self) -> &'static str {
        match self {
            ProcState::Pending => "pending",
            ProcState::Starting { .. } => "starting",
            ProcState::Ready => "ready",
            ProcState::Backoff { .. } => "backoff",
            ProcState::Stopping => "stopping",
            ProcState::Done => "done",
            ProcState::Failed(_) => "FAILED",
        }
    }
    fn is_terminal(&self) -> bool {
        matches!(self, ProcState::Done | ProcState::Failed(_))
    }
}

struct Child {
    plan: PlannedProcess,
    state: ProcState,
    pid: Option<Pid>,
    restarts: u32,
    last_exit: Option<ExitInfo>,
    kill_reason: Option<String>,
    last_heartbeat: Option<Instant>,
    messages: u64,
    rate_base: (Instant, u64),
    rate: f64,
    reports: BTreeMap<u32, StatsReport>,
    stats_in: Input<[u8], MsgHeader>,
    usage: Usage,
}

/// The supervisor of one run.
pub struct Supervisor {
    plan: Plan,
    children: Vec<Child>,
    heartbeats: Input<Heartbeat, MsgHeader>,
    end_of_stream: Input<EndOfStream, MsgHeader>,
    eos_seen: BTreeSet<String>,
    /// Every end of stream seen, by process: replayed to a restarted process once it is ready,
    /// because the instance that died had consumed them.
    eos_messages: BTreeMap<String, EndOfStream>,
    eos_replay: pipeline_runtime::Output<EndOfStream, MsgHeader>,
    /// Processes whose stream the supervisor ended because they failed for good.
    failed_streams: BTreeSet<String>,
    started: Instant,
    last_status: Instant,
    end: Option<EndReason>,
    /// The live status block, when stdout is a terminal ([`crate::live`]).
    live: Option<crate::live::Live>,
}

/// The outcome of a run.
#[derive(Debug, Clone)]
pub struct RunOutcome {
    /// Why it ended.
    pub end: EndReason,
    /// Conventional exit code: 0 ok, 1 a process failed, 128+signal when stopped by a signal.
    pub exit_code: u8,
    /// The summary written to summary.json.
    pub summary: serde_json::Value,
}

impl Supervisor {
    /// Creates the supervisor's node and control ports (before any child exists, so the control
    /// services get the contract's QoS).
    pub fn new(plan: Plan, rt: &mut Runtime) -> anyhow::Result<Self> {
        let heartbeats = rt.input_with_qos::<Heartbeat, MsgHeader>(services::HEARTBEAT, &CONTROL_QOS)?;
        let end_of_stream = rt.input_with_qos::<EndOfStream, MsgHeader>(services::END_OF_STREAM, &CONTROL_QOS)?;
        let eos_replay = rt.output_with_qos::<EndOfStream, MsgHeader>(
            services::END_OF_STREAM,
            &CONTROL_QOS,
            pipeline_runtime::Delivery::DiscardWhenFull,
        )?;
        let now = Instant::now();
        let mut children = vec![];
        for p in &plan.processes {
            let stats_in = rt.input_with_qos::<[u8], MsgHeader>(&services::stats_service(&p.name), &STATS_QOS)?;
            children.push(Child {
                plan: p.clone(),
                state: ProcState::Pending,
                pid: None,
                restarts: 0,
                last_exit: None,
                kill_reason: None,
                last_heartbeat: None,
                messages: 0,
                rate_base: (now, 0),
                rate: 0.0,
                reports: BTreeMap::new(),
                stats_in,
                usage: Usage::default(),
            });
        }
        Ok(Self {
            plan,
            children,
            heartbeats,
            end_of_stream,
            eos_seen: BTreeSet::new(),
            eos_messages: BTreeMap::new(),
            eos_replay,
            failed_streams: BTreeSet::new(),
            started: now,
            last_status: now,
            end: None,
            live: None,
        })
    }

    /// Shows the run in a live status block (stdout a terminal): the processes' output goes to
    /// `<out>/run.log` through it, and the periodic status line is no longer logged.
    pub fn set_live(&mut self, live: crate::live::Live) {
        self.live = Some(live);
    }

    /// Runtime options of the supervisor's own node (it publishes no heartbeat).
    pub fn runtime_options(extra_subscribers: usize) -> RuntimeOptions {
        RuntimeOptions { publish_control: false, extra_subscribers, ..Default::default() }
    }

    /// Runs until the end condition or a signal, then stops every process and reports.
    pub fn run(mut self, rt: &mut Runtime) -> anyhow::Result<RunOutcome> {
        tracing::info!(
            processes = self.children.len(),
            prefix = %self.plan.scope.prefix,
            root = %self.plan.scope.root.display(),
            out = %self.plan.out_dir.display(),
            "starting pipeline"
        );
        let stop = rt.run(&mut self, Some(TICK), |_, sup, _wake| sup.step())?;
        let end = match stop {
            StopReason::Signal(s) => EndReason::Signal(s),
            StopReason::Finished => self.end.clone().unwrap_or(EndReason::AllProcessesEnded),
        };
        tracing::info!(?end, "stopping pipeline");
        self.stop_all();
        self.write_status(true);
        if let Some(l) = self.live.take() {
            self.read_final_stats();
            let rows = self.live_rows();
            l.finish(&rows);
        }
        let failed = self.children.iter().any(|c| matches!(c.state, ProcState::Failed(_)));
        let exit_code = match &end {
            EndReason::Signal(s) => 128 + *s as u8,
            EndReason::RequiredProcessFailed(_) => 1,
            _ if failed => 1,
            _ => 0,
        };
        let rows = self.report_rows();
        // Nothing is lost silently: a warning per service and consumer that missed messages.
        for ((publisher, service, consumer), n) in crate::report::undelivered(&rows) {
            tracing::warn!(
                publisher = %publisher,
                service = %service,
                consumer = %consumer,
                "{n} message(s) of `{service}` from {publisher} never reached {consumer}"
            );
        }
        for ((process, service, reason), n) in crate::report::dropped(&rows) {
            tracing::warn!(
                process = %process,
                service = %service,
                reason = %reason,
                "{process} dropped {n} message(s) of `{service}`: {reason}"
            );
        }
        let summary =
            crate::report::summary(&self.plan, &rows, &end, exit_code, self.started.elapsed(), &self.failed_streams);
        let failed: Vec<String> =
            rows.iter().filter_map(|r| r.failure.map(|why| format!("{} ({why})", r.name))).collect();
        if !failed.is_empty() {
            tracing::error!("the run ended with failed process(es): {}", failed.join("; "));
        }
        Ok(RunOutcome { end, exit_code, summary })
    }

    fn report_rows(&self) -> Vec<crate::report::ProcessRow<'_>> {
        self.children
            .iter()
            .map(|c| crate::report::ProcessRow {
                name: &c.plan.name,
                kind: &c.plan.kind,
                state: c.state.label(),
                failure: match &c.state {
                    ProcState::Failed(why) => Some(why.as_str()),
                    _ => None,
                },
                restarts: c.restarts,
                last_exit: c.last_exit.as_ref(),
                reports: c.reports.values().collect(),
                usage: c.usage,
            })
            .collect()
    }

    /// One pass of the loop: the supervisor's `step`.
    fn step(&mut self) -> anyhow::Result<Flow> {
        let now = Instant::now();
        self.drain_control(now)?;
        self.reap(false);
        self.check_deadlines(now);
        self.start_due(now);
        if let Some(end) = self.end_condition(now) {
            self.end = Some(end);
            return Ok(Flow::Stop);
        }
        let every = self.plan.config.run.status_interval_s;
        if every > 0.0 && now - self.last_status >= Duration::from_secs_f64(every) {
            self.last_status = now;
            self.update_rates(now);
            if self.live.is_none() {
                tracing::info!("{}", self.status_line());
            } else {
                // In run.log only: the block shows it on the terminal.
                tracing::debug!("{}", self.status_line());
            }
            self.write_status(false);
        }
        if self.live.is_some() {
            let rows = self.live_rows();
            if let Some(l) = &mut self.live {
                l.draw(now, &rows);
            }
        }
        Ok(Flow::Continue)
    }

    fn drain_control(&mut self, now: Instant) -> anyhow::Result<()> {
        let mut replay: Vec<String> = vec![];
        while let Some(s) = self.heartbeats.receive()? {
            let hb = *s.payload();
            let name = name_from32(&hb.process);
            let Some(c) = self.children.iter_mut().find(|c| c.plan.name == name) else { continue };
            if c.pid.map(|p| p.as_raw() as u32) != Some(hb.pid) {
                continue; // an earlier instance, or a stray process using the name
            }
            c.last_heartbeat = Some(now);
            c.messages = hb.messages_in + hb.messages_out;
            if hb.state == STATE_READY
                && let ProcState::Starting { since } = c.state
            {
                tracing::info!(process = %name, pid = hb.pid, "ready after {:.0} ms", (now - since).as_secs_f64() * 1e3);
                c.state = ProcState::Ready;
                if c.restarts == 0 {
                    c.usage.ready_rss_mib = rss_mib(hb.pid).unwrap_or(0.0);
                }
                if c.restarts > 0 || !self.failed_streams.is_empty() {
                    replay.push(name.clone());
                }
            }
        }
        // A restarted process missed the ends of stream its dead instance had consumed: send them
        // again (from the supervisor, in the name of the processes that ended).
        // A process started after an upstream failed for good missed that end of stream too.
        for name in replay {
            let restarted = self.children.iter().any(|c| c.plan.name == name && c.restarts > 0);
            for (from, eos) in &self.eos_messages {
                if *from != name && (restarted || self.failed_streams.contains(from)) {
                    tracing::info!(process = %name, from = %from, "replaying end of stream to the restarted process");
                    let now_ns = pipeline_runtime::clock::monotonic_ns();
                    let header = MsgHeader { stamp_ns: now_ns, origin_ns: now_ns, ..Default::default() };
                    if let Err(e) = self.eos_replay.send_value(header, *eos) {
                        tracing::warn!("end of stream not replayed: {e}");
                    }
                }
            }
        }
        while let Some(s) = self.end_of_stream.receive()? {
            let name = name_from32(&s.payload().process);
            tracing::info!(process = %name, last_seq = s.payload().last_seq, "end of stream");
            self.eos_messages.insert(name.clone(), *s.payload());
            self.eos_seen.insert(name);
        }
        self.drain_stats();
        Ok(())
    }

    fn drain_stats(&mut self) {
        for c in &mut self.children {
            loop {
                match c.stats_in.receive() {
                    Ok(Some(s)) => match StatsReport::decode(s.payload()) {
                        Ok(r) if r.process == c.plan.name => {
                            c.reports.insert(r.pid, r);
                        }
                        Ok(r) => tracing::warn!(process = %c.plan.name, "stats report names `{}`; ignored", r.process),
                        Err(e) => tracing::warn!(process = %c.plan.name, "{e}"),
                    },
                    Ok(None) => break,
                    Err(e) => {
                        tracing::warn!(process = %c.plan.name, "{e}");
                        break;
                    }
                }
            }
        }
    }

    /// Collects exited children (without blocking) and applies the restart policy.
    fn reap(&mut self, stopping: bool) {
        let mut exited = false;
        for i in 0..self.children.len() {
            let Some(pid) = self.children[i].pid else { continue };
            let (status, usage) = match wait_with_usage(pid) {
                Ok((WaitStatus::StillAlive, _)) => continue,
                Ok(s) => s,
                Err(e) => {
                    tracing::error!(process = %self.children[i].plan.name, "waitpid: {e}");
                    continue;
                }
            };
            let c = &mut self.children[i];
            if !matches!(status, WaitStatus::Stopped(..) | WaitStatus::Continued(_)) {
                c.usage.cpu_s += usage.cpu_s;
                c.usage.peak_rss_mib = c.usage.peak_rss_mib.max(usage.peak_rss_mib);
            }
            let Some(info) = ExitInfo::from_status(status, c.kill_reason.take()) else { continue };
            c.pid = None;
            exited = true;
            self.on_exit(i, info, stopping);
        }
        if exited {
            match self.plan.scope.cleanup_dead_nodes() {
                Ok(0) => {}
                Ok(n) => tracing::info!("cleaned the iceoryx2 resources of {n} dead node(s)"),
                Err(e) => tracing::warn!("cleaning dead nodes: {e}"),
            }
        }
    }

    fn on_exit(&mut self, i: usize, info: ExitInfo, stopping: bool) {
        let c = &mut self.children[i];
        let name = c.plan.name.clone();
        c.last_heartbeat = None;
        let failure = !info.is_success();
        if stopping || matches!(c.state, ProcState::Stopping) {
            tracing::info!(process = %name, "{}", info.description);
            c.last_exit = Some(info);
            c.state = ProcState::Done;
            return;
        }
        let restart = match c.plan.config.restart {
            RestartPolicy::Never => false,
            RestartPolicy::OnFailure => failure,
            RestartPolicy::Always => true,
        };
        if !restart {
            c.state = if failure { ProcState::Failed(info.description.clone()) } else { ProcState::Done };
            if failure {
                tracing::error!(process = %name, "{}; restart policy {:?}: not restarted", info.description, c.plan.config.restart);
            } else {
                tracing::info!(process = %name, "{}", info.description);
            }
        } else if c.restarts >= c.plan.config.max_restarts {
            let why = format!("{}; gave up after {} restart(s) (max_restarts)", info.description, c.restarts);
            tracing::error!(process = %name, "{why}");
            c.state = ProcState::Failed(why);
        } else {
            let exp = c.restarts.min(20) as i32;
            let delay = (c.plan.config.backoff_initial_s * 2f64.powi(exp)).min(c.plan.config.backoff_max_s);
            c.restarts += 1;
            tracing::warn!(process = %name, "{}; restart {}/{} in {:.2} s", info.description, c.restarts, c.plan.config.max_restarts, delay);
            c.state = ProcState::Backoff { until: Instant::now() + Duration::from_secs_f64(delay) };
        }
        c.last_exit = Some(info);
        if matches!(c.state, ProcState::Failed(_)) {
            self.end_stream_of_failed(i);
        }
    }

    /// A process given up on will never send its end of stream: send it in its name, marked
    /// `EOS_FAILED`, so that its consumers finish with what they have and the run ends.
    fn end_stream_of_failed(&mut self, i: usize) {
        let name = self.children[i].plan.name.clone();
        if self.eos_seen.contains(&name) {
            return; // it had ended its stream before it failed
        }
        let (last_seq, messages_sent) = self.children[i]
            .reports
            .values()
            .flat_map(|r| r.ports.iter().filter(|p| !p.input))
            .fold((0, 0), |(seq, n), p| (seq.max(p.count.saturating_sub(1)), n + p.count));
        // What it published, as its reports say (a process reports its ports from the start of
        // its loop, when every port is open). Without any report (it never got that far: a
        // source that cannot read its file, say) not known: every consumer takes it for an
        // upstream and ends with what it has.
        let reports = &self.children[i].reports;
        let outputs = if reports.is_empty() {
            0
        } else {
            reports
                .values()
                .flat_map(|r| r.ports.iter().filter(|p| !p.input))
                .filter_map(|p| shared_types::services::data_service_bit(&p.service))
                .fold(shared_types::EOS_OUTPUTS_KNOWN, |a, b| a | b)
        };
        let eos = EndOfStream {
            process: shared_types::name32(&name),
            last_seq,
            messages_sent,
            status: shared_types::EOS_FAILED,
            outputs,
        };
        tracing::error!(
            process = %name,
            "{name} failed for good: ending its stream in its name, so that its consumers finish with what it sent"
        );
        let now_ns = pipeline_runtime::clock::monotonic_ns();
        let header = MsgHeader { stamp_ns: now_ns, origin_ns: now_ns, ..Default::default() };
        if let Err(e) = self.eos_replay.send_value(header, eos) {
            tracing::warn!("end of stream of {name} not sent: {e}");
        }
        self.eos_messages.insert(name.clone(), eos);
        self.eos_seen.insert(name.clone());
        self.failed_streams.insert(name);
    }

    fn kill_child(c: &mut Child, reason: String) {
        if let Some(pid) = c.pid {
            tracing::error!(process = %c.plan.name, pid = pid.as_raw(), "{reason}: killing it");
            c.kill_reason = Some(reason);
            let _ = kill(pid, Signal::SIGKILL);
        }
    }

    fn check_deadlines(&mut self, now: Instant) {
        let ready_timeout = Duration::from_secs_f64(self.plan.config.run.ready_timeout_s);
        let hb_timeout = Duration::from_secs_f64(self.plan.config.run.heartbeat_timeout_s);
        for c in &mut self.children {
            if c.kill_reason.is_some() {
                continue; // already killed, waiting to be reaped
            }
            match c.state {
                ProcState::Starting { since } if now - since > ready_timeout => {
                    Self::kill_child(c, format!("not ready within {:.1} s", ready_timeout.as_secs_f64()));
                }
                ProcState::Ready if c.plan.config.heartbeat => {
                    if let Some(last) = c.last_heartbeat
                        && now - last > hb_timeout
                    {
                        Self::kill_child(c, format!("no heartbeat for {:.1} s", (now - last).as_secs_f64()));
                    }
                }
                _ => {}
            }
        }
    }

    fn start_due(&mut self, now: Instant) {
        // A dependency no longer holds a process back once it is ready, or has ended (done, or
        // failed for good: then the process starts without it, with a warning, instead of the
        // run waiting for it until `run.duration_s`).
        let ready: BTreeSet<String> =
            self.children.iter().filter(|c| c.state == ProcState::Ready).map(|c| c.plan.name.clone()).collect();
        let failed: BTreeSet<String> = self
            .children
            .iter()
            .filter(|c| matches!(c.state, ProcState::Failed(_)))
            .map(|c| c.plan.name.clone())
            .collect();
        let done: BTreeSet<String> =
            self.children.iter().filter(|c| c.state == ProcState::Done).map(|c| c.plan.name.clone()).collect();
        for i in 0..self.children.len() {
            let due = match self.children[i].state {
                ProcState::Pending => true,
                ProcState::Backoff { until } => now >= until,
                _ => false,
            };
            let after = &self.children[i].plan.config.after;
            if !due || !after.iter().all(|d| ready.contains(d) || failed.contains(d) || done.contains(d)) {
                continue;
            }
            let missing: Vec<&String> = after.iter().filter(|d| failed.contains(*d)).collect();
            if !missing.is_empty() && self.children[i].state == ProcState::Pending {
                tracing::warn!(
                    process = %self.children[i].plan.name,
                    "starting without {missing:?} (in its `after`), which failed for good"
                );
            }
            if let Err(e) = self.spawn(i) {
                let c = &mut self.children[i];
                tracing::error!(process = %c.plan.name, "cannot start `{}`: {e}", c.plan.binary.display());
                c.state = ProcState::Failed(format!("cannot start: {e}"));
            }
        }
    }

    fn spawn(&mut self, i: usize) -> std::io::Result<()> {
        let out_dir = self.plan.out_dir.clone();
        let scope = self.plan.scope.clone();
        let log_format = self.plan.config.run.log_format;
        let c = &mut self.children[i];
        let mut cmd = Command::new(&c.plan.binary);
        cmd.args(&c.plan.args)
            .stdin(Stdio::null())
            .env(ENV_OUT_DIR, &out_dir)
            .env(ENV_PROCESS_NAME, &c.plan.name)
            .env(ENV_RESTARTS, c.restarts.to_string());
        if c.plan.args.iter().any(|a| a == "--config") {
            cmd.arg("--log-format").arg(match log_format {
                pipeline_runtime::LogFormat::Text => "text",
                pipeline_runtime::LogFormat::Json => "json",
            });
        }
        scope.export_to(&mut cmd);
        // Own process group: a Ctrl-C in the terminal reaches only the supervisor, which then
        // stops the children in reverse dependency order.
        std::os::unix::process::CommandExt::process_group(&mut cmd, 0);
        let parent = std::process::id() as libc::pid_t;
        let nice = c.plan.config.nice;
        // SAFETY: only async-signal-safe calls (prctl, getppid, setpriority, _exit) between fork
        // and exec.
        unsafe {
            std::os::unix::process::CommandExt::pre_exec(&mut cmd, move || {
                // The child dies with the supervisor, even on SIGKILL of the supervisor.
                if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                if libc::getppid() != parent {
                    libc::_exit(1); // the supervisor died between fork and prctl
                }
                // Lower the process's priority (validated 0..=19: never raised).
                if nice > 0 && libc::setpriority(libc::PRIO_PROCESS as _, 0, nice) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
        if self.live.is_some() {
            cmd.stdout(Stdio::piped()).stderr(Stdio::piped());
        }
        let mut child = cmd.spawn()?;
        if let Some(l) = &self.live {
            if let Some(o) = child.stdout.take() {
                l.forward(o);
            }
            if let Some(e) = child.stderr.take() {
                l.forward(e);
            }
        }
        let pid = Pid::from_raw(child.id() as i32);
        drop(child); // reaped with waitpid by pid
        tracing::info!(process = %c.plan.name, pid = pid.as_raw(), restart = c.restarts, "started");
        c.pid = Some(pid);
        c.kill_reason = None;
        c.last_heartbeat = Some(Instant::now());
        c.state =
            if c.plan.config.heartbeat { ProcState::Starting { since: Instant::now() } } else { ProcState::Ready };
        Ok(())
    }

    fn end_condition(&self, now: Instant) -> Option<EndReason> {
        let run = &self.plan.config.run;
        if let Some(c) =
            self.children.iter().find(|c| c.plan.config.required && matches!(c.state, ProcState::Failed(_)))
        {
            return Some(EndReason::RequiredProcessFailed(c.plan.name.clone()));
        }
        if run.duration_s > 0.0 && now - self.started >= Duration::from_secs_f64(run.duration_s) {
            return Some(EndReason::Duration);
        }
        if run.end == EndCondition::EndOfStream {
            let done = if run.end_of_stream_from.is_empty() {
                !self.eos_seen.is_empty()
            } else {
                run.end_of_stream_from.iter().all(|n| self.eos_seen.contains(n))
            };
            if done {
                return Some(EndReason::EndOfStream);
            }
        }
        if self.children.iter().all(|c| c.state.is_terminal()) {
            return Some(EndReason::AllProcessesEnded);
        }
        None
    }

    fn update_rates(&mut self, now: Instant) {
        for c in &mut self.children {
            let (t0, m0) = c.rate_base;
            let dt = (now - t0).as_secs_f64();
            if dt > 0.0 {
                c.rate = c.messages.saturating_sub(m0) as f64 / dt;
            }
            c.rate_base = (now, c.messages);
        }
    }

    /// Writes `<out>/status.json` (atomically: a temporary file renamed) for `supervisor status`:
    /// per process state, restarts, pid, message rate and hop latency.
    pub fn write_status(&self, ended: bool) {
        let processes: Vec<serde_json::Value> = self
            .children
            .iter()
            .map(|c| {
                let current = c.pid.and_then(|p| c.reports.get(&(p.as_raw() as u32)));
                let lat = current.and_then(crate::report::hop_summary).filter(|l| l.count > 0);
                serde_json::json!({
                    "name": c.plan.name,
                    "kind": c.plan.kind,
                    "state": c.state.label(),
                    "restarts": c.restarts,
                    "pid": c.pid.map(|p| p.as_raw()),
                    "messages": c.messages,
                    "messages_per_s": c.rate,
                    "hop_p50_ms": lat.as_ref().map(|l| l.p50),
                    "hop_p99_ms": lat.as_ref().map(|l| l.p99),
                    "e2e_p50_ms": current.and_then(crate::report::e2e_summary).filter(|l| l.count > 0).map(|l| l.p50),
                    "undelivered": undelivered_by(c),
                    "dropped": dropped_by(c),
                })
            })
            .collect();
        let status = serde_json::json!({
            "supervisor_pid": std::process::id(),
            "prefix": self.plan.scope.prefix,
            "uptime_s": self.started.elapsed().as_secs_f64(),
            "updated_unix_ms": std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.as_millis() as u64)
                .unwrap_or(0),
            "status_interval_s": self.plan.config.run.status_interval_s,
            "ended": ended,
            "processes": processes,
        });
        let dir = &self.plan.out_dir;
        let tmp = dir.join(".status.json.tmp");
        let write = std::fs::create_dir_all(dir)
            .and_then(|_| std::fs::write(&tmp, serde_json::to_vec_pretty(&status).unwrap_or_default()))
            .and_then(|_| std::fs::rename(&tmp, dir.join("status.json")));
        if let Err(e) = write {
            tracing::debug!("status.json not written: {e}");
        }
    }

    /// What the live block shows of each process: backlog = messages published on each of its
    /// data inputs (over every publisher's instances, less what never reached it) minus what it
    /// took; control services are left out.
    fn live_rows(&self) -> Vec<crate::live::RowView> {
        let mut published: BTreeMap<(&str, &str), u64> = BTreeMap::new(); // (service, consumer)
        let mut total: BTreeMap<&str, u64> = BTreeMap::new();
        for c in &self.children {
            for r in c.reports.values() {
                for port in r.ports.iter().filter(|p| !p.input) {
                    *total.entry(port.service.as_str()).or_default() += port.count;
                    for (consumer, n) in &port.undelivered_by {
                        *published.entry((port.service.as_str(), consumer.as_str())).or_default() += *n;
                    }
                }
            }
        }
        self.children
            .iter()
            .map(|c| {
                let mut taken: BTreeMap<&str, u64> = BTreeMap::new();
                for r in c.reports.values() {
                    for port in r.ports.iter().filter(|p| p.input) {
                        *taken.entry(port.service.as_str()).or_default() += port.count;
                    }
                }
                // Control services (end of stream, commands) go to whoever listens, not to a queue.
                let backlog = taken
                    .iter()
                    .filter(|(service, _)| !service.starts_with("pipeline/control/"))
                    .map(|(service, got)| {
                        let sent = total.get(service).copied().unwrap_or(0);
                        let missed = published.get(&(*service, c.plan.name.as_str())).copied().unwrap_or(0);
                        sent.saturating_sub(missed).saturating_sub(*got)
                    })
                    .sum();
                let current = c.pid.and_then(|p| c.reports.get(&(p.as_raw() as u32)));
                crate::live::RowView {
                    name: c.plan.name.clone(),
                    state: c.state.label().to_string(),
                    messages: c.reports.values().flat_map(|r| &r.ports).map(|p| p.count).sum(),
                    backlog,
                    dropped: dropped_by(c).values().sum::<u64>() + undelivered_by(c).values().sum::<u64>(),
                    restarts: c.restarts,
                    progress: current.or_else(|| c.reports.values().last()).and_then(|r| r.progress),
                }
            })
            .collect()
    }

    /// The one-line status: per process state, restarts, message rate, p50/p99 hop latency and
    /// p50 end-to-end latency (since the sensor input) of its inputs, and what its outputs did
    /// not deliver (by consumer), as soon as that happens.
    pub fn status_line(&self) -> String {
        let mut parts = vec![format!("t={:.1}s", self.started.elapsed().as_secs_f64())];
        for c in &self.children {
            let mut s = format!("{} {} r{} {:.1} msg/s", c.plan.name, c.state.label(), c.restarts, c.rate);
            let current = c.pid.and_then(|p| c.reports.get(&(p.as_raw() as u32)));
            if let Some(lat) = current.and_then(crate::report::hop_summary)
                && lat.count > 0
            {
                s.push_str(&format!(" hop p50 {:.3} p99 {:.3} ms", lat.p50, lat.p99));
            }
            if let Some(e2e) = current.and_then(crate::report::e2e_summary)
                && e2e.count > 0
            {
                s.push_str(&format!(" e2e p50 {:.1} ms", e2e.p50));
            }
            let lost = undelivered_by(c);
            if !lost.is_empty() {
                let list: Vec<String> = lost.iter().map(|(k, n)| format!("{n} to {k}")).collect();
                s.push_str(&format!(" UNDELIVERED {}", list.join(", ")));
            }
            let dropped = dropped_by(c);
            if !dropped.is_empty() {
                let list: Vec<String> = dropped.iter().map(|(k, n)| format!("{n} {k}")).collect();
                s.push_str(&format!(" DROPPED {}", list.join(", ")));
            }
            parts.push(s);
        }
        parts.join(" | ")
    }

    /// Takes the final reports the processes wrote to `<out>/stats/` at exit: they are complete,
    /// where the last one published may not have been read before its publisher went away.
    fn read_final_stats(&mut self) {
        let dir = self.plan.out_dir.join("stats");
        let Ok(rd) = std::fs::read_dir(&dir) else { return };
        for entry in rd.flatten() {
            let path = entry.path();
            match std::fs::read(&path)
                .map_err(|e| e.to_string())
                .and_then(|b| StatsReport::decode(&b).map_err(|e| e.to_string()))
            {
                Ok(r) => {
                    if let Some(c) = self.children.iter_mut().find(|c| c.plan.name == r.process) {
                        c.reports.insert(r.pid, r);
                    }
                }
                Err(e) => tracing::warn!("{}: {e}", path.display()),
            }
        }
    }

    /// Stops every running process in reverse start order: SIGTERM, then SIGKILL after
    /// `run.stop_timeout_s`; reaps all of them.
    fn stop_all(&mut self) {
        let timeout = Duration::from_secs_f64(self.plan.config.run.stop_timeout_s);
        for i in (0..self.children.len()).rev() {
            match self.children[i].state {
                ProcState::Backoff { .. } | ProcState::Pending => self.children[i].state = ProcState::Done,
                _ => {}
            }
            let Some(pid) = self.children[i].pid else { continue };
            self.children[i].state = ProcState::Stopping;
            let _ = kill(pid, Signal::SIGTERM);
            let deadline = Instant::now() + timeout;
            while self.children[i].pid.is_some() && Instant::now() < deadline {
                std::thread::sleep(Duration::from_millis(5));
                self.drain_stats();
                self.reap(true);
            }
            if let Some(pid) = self.children[i].pid {
                tracing::warn!(process = %self.children[i].plan.name, "did not stop within {:.1} s: SIGKILL", timeout.as_secs_f64());
                self.children[i].kill_reason = Some("stop timeout".into());
                let _ = kill(pid, Signal::SIGKILL);
                while self.children[i].pid.is_some() {
                    std::thread::sleep(Duration::from_millis(5));
                    self.reap(true);
                }
            }
        }
        self.drain_stats();
        self.read_final_stats();
        // Safety net: anything still a child of ours (e.g. spawned but never tracked) is reaped.
        while let Ok(status) = waitpid(None::<Pid>, Some(WaitPidFlag::WNOHANG)) {
            if status == WaitStatus::StillAlive {
                break;
            }
        }
    }
}

/// Messages a process's stage dropped so far (of its inputs, or meant for its outputs), over all its instances, by "service
/// (reason)".
fn dropped_by(c: &Child) -> BTreeMap<String, u64> {
    let mut out: BTreeMap<String, u64> = BTreeMap::new();
    for r in c.reports.values() {
        for port in &r.ports {
            for (reason, n) in &port.dropped_by {
                *out.entry(format!("{} ({reason})", port.service)).or_default() += *n;
            }
        }
    }
    out.retain(|_, n| *n > 0);
    out
}

/// Messages a process's outputs did not deliver so far, over all its instances, by consumer.
fn undelivered_by(c: &Child) -> BTreeMap<String, u64> {
    let mut lost: BTreeMap<String, u64> = BTreeMap::new();
    for r in c.reports.values() {
        for port in r.ports.iter().filter(|p| !p.input) {
            for (consumer, n) in &port.undelivered_by {
                *lost.entry(consumer.clone()).or_default() += *n;
            }
        }
    }
    lost.retain(|_, n| *n > 0);
    lost
}
