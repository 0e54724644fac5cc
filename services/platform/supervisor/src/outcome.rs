//! How processes and runs end, as the supervision loop records them and the report shows them:
//! an instance's exit, its CPU time and memory as the kernel accounts them, why the run ended.

use nix::sys::signal::Signal;
use nix::sys::wait::WaitStatus;
use nix::unistd::Pid;
use serde::Serialize;

/// How a process instance ended.
#[derive(Debug, Clone, Serialize, serde::Deserialize, schemars::JsonSchema, PartialEq)]
pub struct ExitInfo {
    /// Exit code, if it exited.
    pub code: Option<i32>,
    /// Signal number, if a signal ended it.
    pub signal: Option<i32>,
    /// Why the supervisor killed it, if it did.
    pub killed_because: Option<String>,
    /// Human-readable.
    pub description: String,
}

impl ExitInfo {
    pub(crate) fn from_status(status: WaitStatus, killed_because: Option<String>) -> Option<Self> {
        let (code, signal) = match status {
            WaitStatus::Exited(_, c) => (Some(c), None),
            WaitStatus::Signaled(_, s, _) => (None, Some(s as i32)),
            _ => return None,
        };
        let mut description = match (code, signal) {
            (Some(c), _) => format!("exited with code {c}"),
            (_, Some(s)) => {
                format!("killed by signal {s} ({})", Signal::try_from(s).map(|s| s.as_str()).unwrap_or("?"))
            }
            _ => unreachable!(),
        };
        if let Some(k) = &killed_because {
            description = format!("{description} after {k}");
        }
        Some(Self { code, signal, killed_because, description })
    }

    /// A clean exit: code 0 and not killed by the supervisor for a fault.
    pub fn is_success(&self) -> bool {
        self.code == Some(0) && self.killed_because.is_none()
    }
}

/// CPU time and peak memory of a process's ended instances, as the kernel accounts them when
/// the supervisor reaps each one (`wait4`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Usage {
    /// User + system CPU time, s, summed over the instances.
    pub cpu_s: f64,
    /// The largest resident set size of any instance, MiB.
    pub peak_rss_mib: f64,
    /// The resident set size when the first instance reported ready (before any data), MiB, read
    /// from `/proc/<pid>/status`: `peak_rss_mib` less this is what the run's data added.
    pub ready_rss_mib: f64,
}

/// A running process's resident set size, MiB (`VmRSS` in `/proc/<pid>/status`), if readable.
pub(crate) fn rss_mib(pid: u32) -> Option<f64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let kib: f64 =
        status.lines().find_map(|l| l.strip_prefix("VmRSS:"))?.trim().trim_end_matches("kB").trim().parse().ok()?;
    Some(kib / 1024.0)
}

/// `waitpid(pid, WNOHANG)` that also returns the child's resource usage once it has ended.
pub(crate) fn wait_with_usage(pid: Pid) -> nix::Result<(WaitStatus, Usage)> {
    let mut status: libc::c_int = 0;
    // SAFETY: an all-zero rusage is a valid value of the plain C struct that wait4 fills.
    let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: wait4 writes only into `status` and `ru`, both valid for the call.
    let r = unsafe { libc::wait4(pid.as_raw(), &mut status, libc::WNOHANG, &mut ru) };
    if r < 0 {
        return Err(nix::errno::Errno::last());
    }
    if r == 0 {
        return Ok((WaitStatus::StillAlive, Usage::default()));
    }
    let secs = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    let usage = Usage {
        cpu_s: secs(ru.ru_utime) + secs(ru.ru_stime),
        peak_rss_mib: ru.ru_maxrss as f64 / 1024.0, // KiB on Linux
        ready_rss_mib: 0.0,
    };
    Ok((WaitStatus::from_raw(pid, status)?, usage))
}

/// Why the run ended.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum EndReason {
    /// `run.duration_s` elapsed.
    Duration,
    /// The configured processes sent end of stream.
    EndOfStream,
    /// SIGINT/SIGTERM (the signal number).
    Signal(i32),
    /// A `required` process failed.
    RequiredProcessFailed(String),
    /// Every process ended.
    AllProcessesEnded,
}
