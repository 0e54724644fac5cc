//! Harness for multi-process tests: every [`TestRun`] gets its own iceoryx2 prefix and root path
//! and a temporary directory; the processes it starts are killed when it is dropped, and whatever
//! they left in /dev/shm under the prefix is removed then (tests assert cleanliness *before* that).
//!
//! Binaries are taken from the cargo target directory of this build (`target/<profile>/`); build
//! them first (`cargo build --workspace --bins`, which the README's test command does).

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::{Duration, Instant};

use pipeline_runtime::IoxScope;

/// Path of a workspace binary in this build's target directory.
pub fn bin(name: &str) -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    // target/<profile>/deps/<test>-<hash>
    let dir = exe.parent().and_then(Path::parent).expect("target/<profile> directory");
    let path = dir.join(name);
    assert!(
        path.exists(),
        "{} is missing: run `cargo build --workspace --bins` before the tests (the README's test command does)",
        path.display()
    );
    path
}

static COUNTER: AtomicU32 = AtomicU32::new(0);

static HEAVY: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Holds the test binary's one "heavy" slot until dropped. The multi-process tests are one binary
/// whose tests run side by side; a test that runs the whole main job (which alone keeps the two
/// cores busy) or that asserts what arrives through a link cut or a kill takes this first, so that
/// no two of them compete for the CPU and lighter tests still run beside them. A heavy test that
/// failed does not block the others (the lock's poisoning is ignored).
pub fn heavy() -> std::sync::MutexGuard<'static, ()> {
    HEAVY.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// One isolated test run.
pub struct TestRun {
    /// Temporary directory (config, outputs, logs).
    pub dir: tempfile::TempDir,
    /// iceoryx2 scope of the run.
    pub scope: IoxScope,
    supervisor: Option<Child>,
    others: Vec<Child>,
}

impl TestRun {
    /// A new run with a unique prefix derived from `tag`.
    pub fn new(tag: &str) -> Self {
        let n = COUNTER.fetch_add(1, Ordering::Relaxed);
        let tag: String = tag.chars().filter(|c| c.is_ascii_alphanumeric()).take(12).collect();
        let prefix = format!("pt{}_{}_{}_", tag, std::process::id(), n);
        let dir = tempfile::Builder::new().prefix("slam-test-").tempdir().expect("temp dir");
        let root = dir.path().join("iox");
        Self { scope: IoxScope { prefix, root, base_config: None }, dir, supervisor: None, others: vec![] }
    }

    /// Output directory of the run.
    pub fn out_dir(&self) -> PathBuf {
        self.dir.path().join("out")
    }

    /// Writes a pipeline config: a `[run]` table with this run's prefix, root and output
    /// directory plus `run_extra` lines, followed by `processes` (TOML text).
    pub fn write_config(&self, run_extra: &str, processes: &str) -> PathBuf {
        let text = format!(
            "[run]\niceoryx_prefix = \"{}\"\niceoryx_root = \"{}\"\nout_dir = \"{}\"\nstatus_interval_s = 0.5\n{run_extra}\n\n{processes}\n",
            self.scope.prefix,
            self.scope.root.display(),
            self.out_dir().display()
        );
        let path = self.dir.path().join("pipeline.toml");
        std::fs::write(&path, text).expect("write config");
        path
    }

    /// Path of the supervisor's combined log.
    pub fn log_path(&self) -> PathBuf {
        self.dir.path().join("supervisor.log")
    }

    /// Everything the supervisor and its children logged so far.
    pub fn log(&self) -> String {
        std::fs::read_to_string(self.log_path()).unwrap_or_default()
    }

    /// Starts the supervisor on `config` (stdout and stderr, its children's included, go to the log).
    pub fn start_supervisor(&mut self, config: &Path, extra: &[&str]) {
        self.start_supervisor_in(&[], config, extra);
    }

    /// Starts the supervisor under `wrapper` (e.g. `ip netns exec <ns>`, which execs it in a
    /// network namespace: the child is the supervisor itself), as [`TestRun::start_supervisor`].
    pub fn start_supervisor_in(&mut self, wrapper: &[String], config: &Path, extra: &[&str]) {
        let log = std::fs::File::create(self.log_path()).expect("log file");
        let mut cmd = match wrapper.split_first() {
            Some((first, rest)) => {
                let mut c = Command::new(first);
                c.args(rest).arg(bin("supervisor"));
                c
            }
            None => Command::new(bin("supervisor")),
        };
        let child = cmd
            .arg("--config")
            .arg(config)
            .args(extra)
            .env("RUST_LOG", "info")
            .stdin(Stdio::null())
            .stdout(log.try_clone().expect("log fd"))
            .stderr(log)
            .spawn()
            .expect("spawn supervisor");
        self.supervisor = Some(child);
    }

    /// Pid of the supervisor.
    pub fn supervisor_pid(&self) -> i32 {
        self.supervisor.as_ref().expect("supervisor started").id() as i32
    }

    /// Sends `sig` to the supervisor.
    pub fn signal_supervisor(&self, sig: nix::sys::signal::Signal) {
        nix::sys::signal::kill(nix::unistd::Pid::from_raw(self.supervisor_pid()), sig).expect("signal supervisor");
    }

    /// Waits up to `timeout` for the supervisor to exit.
    pub fn wait_supervisor(&mut self, timeout: Duration) -> Option<ExitStatus> {
        let child = self.supervisor.as_mut().expect("supervisor started");
        let end = Instant::now() + timeout;
        while Instant::now() < end {
            if let Some(s) = child.try_wait().expect("try_wait") {
                return Some(s);
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        None
    }

    /// Waits until the log contains `needle` `times` times; panics with the log on timeout.
    pub fn wait_for_log(&self, needle: &str, times: usize, timeout: Duration) {
        let end = Instant::now() + timeout;
        while Instant::now() < end {
            if self.log().matches(needle).count() >= times {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        panic!("timed out waiting for {times}× `{needle}` in the log:\n{}", self.log());
    }

    /// Pids the supervisor logged as `started process=<name> pid=<pid>`, in order.
    pub fn started_pids(&self, name: &str) -> Vec<i32> {
        let needle = format!("process={name} pid=");
        self.log()
            .lines()
            .filter(|l| l.contains("started") && l.contains(&needle))
            .filter_map(|l| l.split(&needle).nth(1)?.split_whitespace().next()?.parse().ok())
            .collect()
    }

    /// summary.json of the run.
    pub fn summary(&self) -> serde_json::Value {
        let path = self.out_dir().join("summary.json");
        let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}\nlog:\n{}", path.display(), self.log()));
        serde_json::from_slice(&bytes).expect("summary.json is JSON")
    }

    /// Files of this run's prefix in /dev/shm and files under its root path.
    pub fn leftovers(&self) -> Vec<PathBuf> {
        let mut v = self.scope.shm_files();
        fn walk(d: &Path, v: &mut Vec<PathBuf>) {
            if let Ok(rd) = std::fs::read_dir(d) {
                for e in rd.flatten() {
                    if e.path().is_dir() { walk(&e.path(), v) } else { v.push(e.path()) }
                }
            }
        }
        walk(&self.scope.root, &mut v);
        v
    }

    /// Runs the supervisor on a config with `run_extra` and `processes` to its end (at most
    /// `timeout`), asserts a clean exit (code 0, nothing left in /dev/shm or the root path), and
    /// returns summary.json.
    pub fn run_to_end(&mut self, run_extra: &str, processes: &str, timeout: Duration) -> serde_json::Value {
        let cfg = self.write_config(run_extra, processes);
        self.start_supervisor(&cfg, &[]);
        let status = self.wait_supervisor(timeout).expect("the run ends");
        assert_eq!(status.code(), Some(0), "{}", self.log());
        assert_eq!(self.leftovers(), Vec::<PathBuf>::new(), "iceoryx2 files left behind");
        self.summary()
    }

    /// Spawns another process that is killed on drop; stdout is piped.
    pub fn spawn(&mut self, cmd: &mut Command) -> &mut Child {
        let child = cmd.stdin(Stdio::null()).stdout(Stdio::piped()).spawn().expect("spawn");
        self.others.push(child);
        self.others.last_mut().expect("just pushed")
    }
}

impl TestRun {
    /// A process started with [`TestRun::spawn`], by pid.
    pub fn others_mut(&mut self, pid: u32) -> &mut Child {
        self.others.iter_mut().find(|c| c.id() == pid).expect("spawned by this run")
    }
}

/// Reads lines from a child's stdout until one equals `line` (or panics after `timeout`).
pub fn wait_for_line(child: &mut Child, line: &str, timeout: Duration) -> Vec<String> {
    let stdout = child.stdout.take().expect("stdout piped");
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for l in BufReader::new(stdout).lines().map_while(Result::ok) {
            if tx.send(l).is_err() {
                break;
            }
        }
    });
    let end = Instant::now() + timeout;
    let mut seen = vec![];
    while let Some(left) = end.checked_duration_since(Instant::now()) {
        match rx.recv_timeout(left) {
            Ok(l) => {
                let done = l == line;
                seen.push(l);
                if done {
                    // keep draining in the background so the child never blocks on a full pipe
                    std::thread::spawn(move || while rx.recv().is_ok() {});
                    return seen;
                }
            }
            Err(_) => break,
        }
    }
    panic!("timed out waiting for line `{line}`; got {seen:?}");
}

/// True while a process exists and is not a zombie.
pub fn process_alive(pid: i32) -> bool {
    match std::fs::read_to_string(format!("/proc/{pid}/stat")) {
        Ok(stat) => stat.rsplit(')').next().and_then(|r| r.split_whitespace().next()) != Some("Z"),
        Err(_) => false,
    }
}

impl Drop for TestRun {
    fn drop(&mut self) {
        for c in self.others.iter_mut().chain(self.supervisor.iter_mut()) {
            let _ = c.kill();
            let _ = c.wait();
        }
        // Children of a killed supervisor die with it (PDEATHSIG); give them a moment.
        std::thread::sleep(Duration::from_millis(50));
        let _ = self.scope.cleanup_dead_nodes();
        let _ = self.scope.remove_all_resources();
    }
}

/// A network namespace of its own with only loopback (up, multicast on, the multicast range
/// routed to it), deleted on drop: DDS discovery inside it reaches nothing outside the
/// namespace. `None` when this user may not make one (not root, or `ip netns` failed).
pub struct NetNs {
    /// The namespace's name.
    pub name: String,
}

fn ip_ok(args: &[&str]) -> bool {
    Command::new("ip").args(args).stdout(Stdio::null()).stderr(Stdio::null()).status().is_ok_and(|s| s.success())
}

impl NetNs {
    /// Makes the namespace `<tag><pid>`.
    pub fn new(tag: &str) -> Option<Self> {
        // SAFETY: geteuid has no preconditions and cannot fail.
        if unsafe { libc::geteuid() } != 0 {
            return None;
        }
        let n = COUNTER.fetch_add(1, Ordering::Relaxed);
        let name = format!("{tag}{}n{n}", std::process::id() % 100_000);
        if !ip_ok(&["netns", "add", &name]) {
            return None;
        }
        let ns = Self { name };
        let ok = ip_ok(&["-n", &ns.name, "link", "set", "lo", "up"])
            && ip_ok(&["-n", &ns.name, "link", "set", "lo", "multicast", "on"])
            && ip_ok(&["-n", &ns.name, "route", "add", "224.0.0.0/4", "dev", "lo"]);
        ok.then_some(ns)
    }

    /// Like [`NetNs::new`], but panics with what is needed when the namespace cannot be made.
    pub fn required(tag: &str) -> Self {
        Self::new(tag).unwrap_or_else(|| {
            panic!(
                "this test needs a network namespace of its own (DDS discovery must not reach the machine's \
                 interfaces): run the tests as root with iproute2 (`ip netns add` failed or is not permitted)"
            )
        })
    }

    /// The command prefix that runs a program inside the namespace.
    pub fn wrapper(&self) -> Vec<String> {
        vec!["ip".into(), "netns".into(), "exec".into(), self.name.clone()]
    }

    /// A command that runs `program` inside the namespace.
    pub fn command(&self, program: &str) -> Command {
        let mut c = Command::new("ip");
        c.args(["netns", "exec", &self.name, program]);
        c
    }
}

impl Drop for NetNs {
    fn drop(&mut self) {
        ip_ok(&["netns", "del", &self.name]);
    }
}

/// A `grid_slam` process named `slam2d`, scored against the Freiburg 079 relations of `data`
/// (the shared `data/carmen` folder), with `particles` on `threads`, publishing its grid every
/// `grid_every_s` of data time.
pub fn fr079_grid_slam(data: &str, particles: u32, threads: u32, grid_every_s: f64) -> String {
    format!(
        r#"
[processes.slam2d]
kind = "grid_slam"
[processes.slam2d.settings]
relations = "{data}/fr079.relations"
relations_offset_s = 1211.38
grid_every_s = {grid_every_s:?}
[processes.slam2d.settings.filter]
particles = {particles}
threads = {threads}
"#
    )
}

/// An `ingest` process started after `slam2d`, replaying as fast as possible; `source` holds the
/// source's settings lines (`source = ...` and its table).
pub fn ingest_after_slam2d(source: &str) -> String {
    format!(
        r#"
[processes.ingest]
kind = "ingest"
after = ["slam2d"]
[processes.ingest.settings]
real_time_factor = 0.0
{source}
"#
    )
}

/// The first `max_scans` scans of the CARMEN `log`, the laser lines' odometry as it is.
pub fn carmen_source(log: &str, max_scans: usize) -> String {
    format!(
        "source = \"carmen\"\n[processes.ingest.settings.carmen]\nfile = \"{log}\"\nodometry = \"laser_lines\"\nmax_scans = {max_scans}\n"
    )
}
