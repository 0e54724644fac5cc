//! The consumer child process as the parent sees it: spawned from this same executable in the
//! benchmark's iceoryx2 scope, its stdout read line by line on a helper thread, killed on drop.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::mpsc::{Receiver, RecvTimeoutError, channel};
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail};
use pipeline_runtime::IoxScope;

use crate::cli::Transport;

/// A running child process of a benchmark (a consumer, or a relay of a chain) whose stdout is read
/// line by line; SIGKILLed and reaped on drop if it is still running.
pub struct ConsumerProcess {
    child: Child,
    lines: Receiver<String>,
    label: String,
}

impl ConsumerProcess {
    /// Starts `current_exe() consumer ...` for `transport` in `scope` (and on `socket`, if given).
    pub fn spawn(
        transport: Transport,
        points: usize,
        warmup: u64,
        scope: &IoxScope,
        socket: Option<&Path>,
    ) -> anyhow::Result<Self> {
        let exe = std::env::current_exe().context("cannot find this executable to start the consumer")?;
        let mut cmd = Command::new(&exe);
        cmd.arg("consumer")
            .args(["--transport", transport.name()])
            .args(["--points", &points.to_string()])
            .args(["--warmup", &warmup.to_string()])
            .args(["--parent-pid", &std::process::id().to_string()])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit());
        if let Some(s) = socket {
            cmd.arg("--socket").arg(s);
        }
        scope.export_to(&mut cmd);
        Self::spawn_command(cmd, format!("{} consumer", transport.name()))
    }

    /// Starts `cmd` with its stdout piped (stdin null, stderr inherited); `label` names it in errors.
    pub fn spawn_command(mut cmd: Command, label: String) -> anyhow::Result<Self> {
        cmd.stdin(Stdio::null()).stdout(Stdio::piped()).stderr(Stdio::inherit());
        let mut child = cmd.spawn().with_context(|| format!("cannot start the {label} ({:?})", cmd.get_program()))?;
        let stdout = child.stdout.take().context("consumer stdout was not captured")?;
        let (tx, lines) = channel();
        std::thread::Builder::new()
            .name("consumer-stdout".into())
            .spawn(move || {
                for line in BufReader::new(stdout).lines() {
                    let Ok(line) = line else { break };
                    if tx.send(line).is_err() {
                        break;
                    }
                }
            })
            .context("cannot start the thread reading the consumer's output")?;
        Ok(Self { child, lines, label })
    }

    /// Waits up to `timeout` for a stdout line starting with `prefix` and returns the rest of it.
    /// `cancel` is polled every 100 ms: a `Some(signal)` aborts the wait.
    pub fn wait_line(
        &mut self,
        prefix: &str,
        timeout: Duration,
        cancel: &dyn Fn() -> Option<i32>,
    ) -> anyhow::Result<String> {
        let end = Instant::now() + timeout;
        loop {
            if let Some(sig) = cancel() {
                bail!("interrupted by signal {sig}");
            }
            let left = end.saturating_duration_since(Instant::now());
            if left.is_zero() {
                bail!("the {} did not say `{}` within {:?}", self.label, prefix.trim(), timeout);
            }
            match self.lines.recv_timeout(left.min(Duration::from_millis(100))) {
                Ok(line) => {
                    if let Some(rest) = line.strip_prefix(prefix) {
                        return Ok(rest.to_string());
                    }
                    tracing::warn!(child = self.label, "unexpected output: {line}");
                }
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => {
                    let status = self.wait_exit(Duration::from_secs(5)).map(|s| s.to_string());
                    bail!(
                        "the {} exited before saying `{}` ({})",
                        self.label,
                        prefix.trim(),
                        status.unwrap_or_else(|e| format!("{e:#}"))
                    );
                }
            }
        }
    }

    /// Waits up to `timeout` for the consumer to exit.
    pub fn wait_exit(&mut self, timeout: Duration) -> anyhow::Result<ExitStatus> {
        let end = Instant::now() + timeout;
        loop {
            if let Some(status) = self.child.try_wait().context("waiting for the consumer")? {
                return Ok(status);
            }
            if Instant::now() >= end {
                bail!("the {} did not exit within {timeout:?}", self.label);
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }
}

impl Drop for ConsumerProcess {
    fn drop(&mut self) {
        if matches!(self.child.try_wait(), Ok(None)) {
            let _ = self.child.kill();
        }
        let _ = self.child.wait();
    }
}
