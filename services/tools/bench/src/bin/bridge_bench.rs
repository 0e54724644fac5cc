//! `bridge_bench`: latency and throughput across the Zenoh bridge against a bare Zenoh
//! publisher/subscriber pair, for messages from a cloud header alone (96 B) to a 300k-point
//! cloud (3.6 MB), in one run, on this machine's loopback.
//!
//! - **bare Zenoh**: this process puts the bytes on a key; a child process (`bridge_bench
//!   zenoh-sub`, its own session, TCP over 127.0.0.1) receives them. Latency = the child's
//!   CLOCK_MONOTONIC at receipt − the send time written in the payload's first 8 bytes.
//! - **bridge**: this process publishes a cloud into iceoryx2 (prefix A, written in place in a
//!   loaned sample); a `bridge` process of prefix A sends it to Zenoh; a `bridge` process of
//!   prefix B receives it and publishes it into a loaned sample of prefix B; a thread of this
//!   process receives it there. Latency = receipt − the header's `origin_ns` (kept by the bridge).
//!   So the bridge row has two processes and two iceoryx2 hops more than the bare row: what a
//!   pipeline pays to reach another host.
//!
//! - **tls**: the bridge row again over mutual TLS (certificates made by `supervisor certs`,
//!   docs/security.md); `tls/tcp` is its ratio to the plain-TCP bridge row of the same size.
//!
//! The plain-TCP and TLS bridge rows run in turn for `--rounds` rounds (3): their ratios are the
//! median of the rounds' ratios, with the range, so that load drifting between rows decides less.
//!
//! One message in flight at `--rate-hz` for latency; then a burst of messages back to back
//! (reliable: Zenoh congestion control `Block` on both rows) for throughput. Both clocks are this
//! machine's, so one-way latency is exact.
//!
//! `--shape "<tc qdisc>"` (repeatable, as root) also runs every row across a shaped link: the
//! receiving side (the bare row's subscriber, the receiving bridge) in a network namespace of its
//! own, joined to this one by a veth pair whose sending end gets the qdisc (e.g. `netem delay
//! 20ms loss 1%`, `tbf rate 20mbit burst 64kb latency 100ms`). A qdisc the kernel lacks (netem
//! needs the sch_netem module) is reported and skipped.
//! Each row's iceoryx2 files are removed from /dev/shm when it ends.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail};
use clap::{Parser, Subcommand};
use pipeline_runtime::{Delivery, Flow, IoxScope, Runtime, RuntimeOptions, StageError, monotonic_ns};
use shared_types::services::{CLOUD, service_spec};
use shared_types::{CloudHeader, CloudPoint, MsgHeader};
use zenoh::Wait;
use zenoh::qos::CongestionControl;

#[derive(Parser)]
#[command(about = "Latency and throughput across the Zenoh bridge against bare Zenoh, on loopback")]
struct Cli {
    #[command(subcommand)]
    child: Option<ChildCommand>,
    /// Message sizes, bytes (the bridge rows send a cloud of 96 + 12·n bytes, the nearest below).
    #[arg(long, value_delimiter = ',', default_value = "96,65536,1048576,3600000")]
    sizes: Vec<usize>,
    /// Measured messages per size and row (after 20 warm-up ones).
    #[arg(long, default_value_t = 200)]
    samples: usize,
    /// Message rate of the latency phase, Hz.
    #[arg(long, default_value_t = 50.0)]
    rate_hz: f64,
    /// Bytes sent back to back for throughput, per size and row (20 to 20,000 messages).
    #[arg(long, default_value_t = 200_000_000)]
    burst_bytes: usize,
    /// Also run the rows across a veth link shaped by this `tc qdisc` (e.g. "netem delay 20ms
    /// loss 1%"); repeatable; needs root.
    #[arg(long)]
    shape: Vec<String>,
    /// Rounds of the plain-TCP and TLS bridge rows, in turn (tcp, tls, tcp, tls, ...): the
    /// `tls/tcp` ratios are the median over the rounds of each round's ratio, with their range,
    /// so that the machine's load drifting between two rows does not decide the ratio.
    #[arg(long, default_value_t = 3)]
    rounds: usize,
    /// Keep the bridges' logs (stderr) in this directory, one file per bridge and row, instead of
    /// discarding them: to see what a bridge said about a message that did not arrive.
    #[arg(long)]
    logs: Option<std::path::PathBuf>,
}

/// Where the receiving side runs: this network namespace (loopback) or another one behind a veth.
struct Net {
    /// The receiving side's address.
    host: String,
    /// Prefix of the receiving side's command (`ip netns exec <ns>`), empty on loopback.
    wrap: Vec<String>,
}

impl Net {
    fn loopback() -> Self {
        Self { host: "127.0.0.1".into(), wrap: vec![] }
    }

    fn command(&self, program: &std::path::Path) -> Command {
        match self.wrap.split_first() {
            None => Command::new(program),
            Some((first, rest)) => {
                let mut c = Command::new(first);
                c.args(rest).arg(program);
                c
            }
        }
    }
}

/// A network namespace joined to this one by a veth pair whose end here is shaped by a qdisc
/// (deleted on drop).
struct Shaped {
    ns: String,
    net: Net,
}

fn run_ip(args: &[&str]) -> Result<(), String> {
    let out = Command::new(args[0]).args(&args[1..]).output().map_err(|e| format!("{}: {e}", args[0]))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!("`{}`: {}", args.join(" "), String::from_utf8_lossy(&out.stderr).trim()))
    }
}

impl Shaped {
    fn new(qdisc: &str, n: usize) -> Result<Self, String> {
        // SAFETY: geteuid has no preconditions and cannot fail.
        if unsafe { libc::geteuid() } != 0 {
            return Err("network namespaces need root".into());
        }
        let tag = format!("pbb{}s{n}", std::process::id() % 100_000);
        let (ns, here, there) = (format!("{tag}n"), format!("{tag}a"), format!("{tag}b"));
        let net = format!("10.214.{}", (std::process::id() as usize + n) % 250);
        run_ip(&["ip", "netns", "add", &ns])?;
        let shaped = Self {
            ns: ns.clone(),
            net: Net {
                host: format!("{net}.2"),
                wrap: ["ip", "netns", "exec", &ns].iter().map(|s| s.to_string()).collect(),
            },
        };
        run_ip(&["ip", "link", "add", &here, "type", "veth", "peer", "name", &there])?;
        run_ip(&["ip", "link", "set", &there, "netns", &ns])?;
        run_ip(&["ip", "addr", "add", &format!("{net}.1/24"), "dev", &here])?;
        run_ip(&["ip", "link", "set", &here, "up"])?;
        run_ip(&["ip", "-n", &ns, "addr", "add", &format!("{net}.2/24"), "dev", &there])?;
        run_ip(&["ip", "-n", &ns, "link", "set", &there, "up"])?;
        run_ip(&["ip", "-n", &ns, "link", "set", "lo", "up"])?;
        let mut tc = vec!["tc", "qdisc", "add", "dev", &here, "root"];
        tc.extend(qdisc.split_whitespace());
        run_ip(&tc)?;
        Ok(shaped)
    }
}

impl Drop for Shaped {
    fn drop(&mut self) {
        // Deleting the namespace deletes its veth end and so the pair.
        let _ = run_ip(&["ip", "netns", "del", &self.ns]);
    }
}

#[derive(Subcommand)]
enum ChildCommand {
    /// (internal) Subscribes `key` on a session listening on `listen`; prints the result as JSON.
    ZenohSub {
        /// Endpoint to listen on.
        #[arg(long)]
        listen: String,
        /// Key to subscribe.
        #[arg(long)]
        key: String,
        /// Latency messages to wait for.
        #[arg(long)]
        latency: usize,
        /// Burst messages to wait for.
        #[arg(long)]
        burst: usize,
    },
}

/// What a receiver saw: latencies (µs) of the latency phase, and the burst's messages and span.
#[derive(Debug, Default, serde::Serialize, serde::Deserialize)]
struct Seen {
    latencies_us: Vec<f64>,
    /// Bridge row: of each latency, the last iceoryx2 hop (the receiving bridge's `publish_ns` to
    /// receipt); the rest is the sending side, Zenoh and the receiving bridge.
    #[serde(default)]
    last_hop_us: Vec<f64>,
    burst_messages: usize,
    burst_s: f64,
}

impl Seen {
    /// Adds another run's measurements of the same row (latencies pooled, burst spans summed).
    fn pool(&mut self, other: Seen) {
        self.latencies_us.extend(other.latencies_us);
        self.last_hop_us.extend(other.last_hop_us);
        self.burst_messages += other.burst_messages;
        self.burst_s += other.burst_s;
    }
}

/// Flag of a message: a probe (not counted), a latency sample, or part of the burst.
const PROBE: u8 = 0;
const SAMPLE: u8 = 1;
const BURST: u8 = 2;

fn zerr(e: impl std::fmt::Display) -> anyhow::Error {
    anyhow::anyhow!("zenoh: {e}")
}

fn zenoh_config(listen: Option<&str>, connect: Option<&str>) -> anyhow::Result<zenoh::Config> {
    let mut c = zenoh::Config::default();
    let mut set = |k: &str, v: String| c.insert_json5(k, &v).map_err(|e| anyhow::anyhow!("{k}: {e}"));
    set("mode", "\"peer\"".into())?;
    set("scouting/multicast/enabled", "false".into())?;
    if let Some(l) = listen {
        set("listen/endpoints", format!("[\"{l}\"]"))?;
    }
    if let Some(e) = connect {
        set("connect/endpoints", format!("[\"{e}\"]"))?;
    }
    Ok(c)
}

/// The child of the bare row.
fn zenoh_sub(listen: &str, key: &str, latency: usize, burst: usize) -> anyhow::Result<()> {
    let s = zenoh::open(zenoh_config(Some(listen), None)?).wait().map_err(zerr)?;
    let (tx, rx) = std::sync::mpsc::channel::<(u64, u64, u8)>();
    let _sub = s
        .declare_subscriber(key)
        .callback(move |sample| {
            let now = monotonic_ns();
            let b = sample.payload().to_bytes();
            if b.len() >= 9 {
                let sent = u64::from_le_bytes(b[..8].try_into().unwrap_or_default());
                let _ = tx.send((now, sent, b[8]));
            }
        })
        .wait()
        .map_err(zerr)?;
    println!("ready");
    let mut seen = Seen::default();
    let mut burst_start = None;
    let deadline = Instant::now() + Duration::from_secs(600);
    while seen.latencies_us.len() < latency || seen.burst_messages < burst {
        let Ok((now, sent, flag)) = rx.recv_timeout(deadline.saturating_duration_since(Instant::now())) else {
            bail!("timed out after {} latency and {} burst messages", seen.latencies_us.len(), seen.burst_messages)
        };
        match flag {
            SAMPLE => seen.latencies_us.push(now.saturating_sub(sent) as f64 / 1e3),
            BURST => {
                let start = *burst_start.get_or_insert(sent);
                seen.burst_messages += 1;
                seen.burst_s = now.saturating_sub(start) as f64 / 1e9;
            }
            _ => {}
        }
    }
    println!("{}", serde_json::to_string(&seen)?);
    Ok(())
}

/// A child process, stopped (SIGTERM, so that a pipeline process removes its iceoryx2 files; SIGKILL
/// after 5 s) and reaped on drop.
struct Killed(Child);

impl Drop for Killed {
    fn drop(&mut self) {
        // SAFETY: kill(2) on our own child's pid; no memory is involved.
        unsafe { libc::kill(self.0.id() as libc::pid_t, libc::SIGTERM) };
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(5) {
            if matches!(self.0.try_wait(), Ok(Some(_))) {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Removes an iceoryx2 scope's files from /dev/shm and its root path on drop (after the row's
/// processes ended).
struct RemoveFiles(IoxScope);

impl Drop for RemoveFiles {
    fn drop(&mut self) {
        let _ = self.0.remove_all_resources();
    }
}

fn free_port() -> anyhow::Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port())
}

/// A message of `size` bytes: the same kind of bytes as the bridge row's cloud (not a zeroed
/// buffer: the kernel maps fresh zero pages to one shared page, which makes copying it look cheap),
/// stamped with the send time when it is complete.
fn message(size: usize, flag: u8) -> Vec<u8> {
    let mut v: Vec<u8> = (0..size.max(9)).map(|i| (i as u32).wrapping_mul(2_654_435_761).to_le_bytes()[3]).collect();
    v[8] = flag;
    v[..8].copy_from_slice(&monotonic_ns().to_le_bytes());
    v
}

/// The bare Zenoh row for one size.
fn bare(size: usize, cli: &Cli, burst: usize, net: &Net) -> anyhow::Result<Seen> {
    let port = free_port()?;
    let exe = std::env::current_exe()?;
    let host = &net.host;
    let mut child = Killed(
        net.command(&exe)
            .args(["zenoh-sub", "--listen", &format!("tcp/{host}:{port}"), "--key", "bench/bare"])
            .args(["--latency", &cli.samples.to_string(), "--burst", &burst.to_string()])
            .stdout(Stdio::piped())
            .spawn()?,
    );
    let mut lines = BufReader::new(child.0.stdout.take().context("stdout")?).lines();
    if lines.next().transpose()?.as_deref() != Some("ready") {
        bail!("the subscriber did not start");
    }
    let s = zenoh::open(zenoh_config(None, Some(&format!("tcp/{host}:{port}")))?).wait().map_err(zerr)?;
    let p = s.declare_publisher("bench/bare").congestion_control(CongestionControl::Block).wait().map_err(zerr)?;
    let t0 = Instant::now();
    while !p.matching_status().wait().map_err(zerr)?.matching() {
        if t0.elapsed() > Duration::from_secs(30) {
            bail!("no subscriber matched");
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    let period = Duration::from_secs_f64(1.0 / cli.rate_hz);
    for k in 0..20 + cli.samples {
        p.put(message(size, if k < 20 { PROBE } else { SAMPLE })).wait().map_err(zerr)?;
        std::thread::sleep(period);
    }
    for _ in 0..burst {
        p.put(message(size, BURST)).wait().map_err(zerr)?;
    }
    let line = lines.next().transpose()?.context("the subscriber ended without a result")?;
    Ok(serde_json::from_str(&line)?)
}

/// Writes a pipeline config with one bridge process `link` in `scope`.
fn bridge_config(
    dir: &std::path::Path,
    name: &str,
    scope: &IoxScope,
    settings: &str,
) -> anyhow::Result<std::path::PathBuf> {
    let text = format!(
        "[run]\niceoryx_prefix = \"{}\"\niceoryx_root = \"{}\"\nout_dir = \"{}\"\n\n[processes.link]\nkind = \"bridge\"\n\
         [processes.link.settings]\n{settings}\n",
        scope.prefix,
        scope.root.display(),
        dir.join(format!("out_{name}")).display()
    );
    let path = dir.join(format!("{name}.toml"));
    std::fs::write(&path, text)?;
    Ok(path)
}

/// The bridge row for one size: (what arrived, the message size sent).
fn bridged(
    size: usize,
    cli: &Cli,
    burst: usize,
    dir: &std::path::Path,
    n: usize,
    net: &Net,
    tls: Option<&std::path::Path>,
) -> anyhow::Result<(Seen, usize)> {
    let port = free_port()?;
    let scope = |tag: &str| IoxScope {
        prefix: format!("pbb{tag}{}_{n}_", std::process::id()),
        root: dir.join(format!("iox_{tag}{n}")),
        base_config: None,
    };
    let (a, b) = (scope("a"), scope("b"));
    // Declared before every process and runtime of the row, so dropped after them all.
    let _files = (RemoveFiles(a.clone()), RemoveFiles(b.clone()));
    let bin = std::env::current_exe()?.parent().context("bin dir")?.join("bridge");
    if !bin.exists() {
        bail!("{} is missing: build it (cargo build --release --workspace --bins)", bin.display());
    }
    let (ca, cb) = link_configs(dir, n, &net.host, port, tls, &a, &b)?;
    let _rb = spawn_bridge(&bin, &cb, net, cli.logs.as_deref())?;
    // The receiving side: a thread with its own runtime in prefix B.
    let receiver = spawn_receiver(b.clone(), cli.samples, burst)?;
    let _ra = spawn_bridge(&bin, &ca, &Net::loopback(), cli.logs.as_deref())?;
    let points = size.saturating_sub(96) / 12;
    let seen = send_row(&a, points, cli, burst, receiver)?;
    Ok((seen, 96 + 12 * points))
}

/// The two bridges' configs: robot `r` sends the clouds of prefix `a`, the base receives them into
/// prefix `b`, over plain TCP (`insecure`) or mutual TLS with the certificates in `tls`.
fn link_configs(
    dir: &std::path::Path,
    n: usize,
    host: &str,
    port: u16,
    tls: Option<&std::path::Path>,
    a: &IoxScope,
    b: &IoxScope,
) -> anyhow::Result<(std::path::PathBuf, std::path::PathBuf)> {
    let link = |name: &str| match tls {
        None => "insecure = true".to_string(),
        Some(d) => format!(
            "tls = {{ ca_certificate = {:?}, certificate = {:?}, private_key = {:?} }}",
            d.join("ca.pem"),
            d.join(format!("{name}.pem")),
            d.join(format!("{name}.key"))
        ),
    };
    let proto = if tls.is_some() { "tls" } else { "tcp" };
    let ca = bridge_config(
        dir,
        &format!("a{n}{proto}"),
        a,
        &format!(
            "robot = \"r\"\nend_ack_timeout_s = 0\nzenoh = {{ connect = [\"{proto}/{host}:{port}\"], {} }}\n\
             out = [{{ service = \"{CLOUD}\" }}]",
            link("r")
        ),
    )?;
    let cb = bridge_config(
        dir,
        &format!("b{n}{proto}"),
        b,
        &format!(
            "zenoh = {{ listen = [\"{proto}/{host}:{port}\"], {} }}\n\
             accept = {{ max_rate_hz = 0 }}\nin = [{{ from = \"r\", service = \"{CLOUD}\" }}]",
            link("base")
        ),
    )?;
    Ok((ca, cb))
}

/// Starts a bridge process on `cfg` in `net` (its stderr into `logs` when given), killed on drop.
fn spawn_bridge(
    bin: &std::path::Path,
    cfg: &std::path::Path,
    net: &Net,
    logs: Option<&std::path::Path>,
) -> anyhow::Result<Killed> {
    let stderr = match logs {
        None => Stdio::null(),
        Some(d) => {
            std::fs::create_dir_all(d)?;
            let name = cfg.file_stem().and_then(|n| n.to_str()).unwrap_or("bridge");
            let file = d.join(format!("{}_{name}.log", std::process::id()));
            std::fs::File::create(&file).with_context(|| format!("{}", file.display()))?.into()
        }
    };
    Ok(Killed(
        net.command(bin)
            .arg("--config")
            .arg(cfg)
            .args(["--name", "link"])
            .stdout(Stdio::null())
            .stderr(stderr)
            .spawn()?,
    ))
}

/// A thread with its own runtime in prefix `b` that takes the clouds: the samples' latencies and
/// the burst's duration. Returns once its subscriber is open.
fn spawn_receiver(
    b: IoxScope,
    samples: usize,
    burst: usize,
) -> anyhow::Result<std::thread::JoinHandle<anyhow::Result<Seen>>> {
    let (ready_tx, ready_rx) = std::sync::mpsc::channel::<()>();
    let receiver = std::thread::spawn(move || -> anyhow::Result<Seen> {
        let options = RuntimeOptions { publish_control: false, ..Default::default() };
        let mut rt = Runtime::new("bench_rx", &b, options)?;
        let input = rt.input::<[CloudPoint], CloudHeader>(CLOUD)?;
        let _ = ready_tx.send(());
        let mut seen = Seen::default();
        let mut burst_start = None;
        let mut last = Instant::now();
        rt.run(&mut seen, Some(Duration::from_millis(100)), |_, seen, _| {
            while let Some(s) = input.receive()? {
                let now = monotonic_ns();
                let h = *s.user_header();
                match h.flags as u8 {
                    SAMPLE => {
                        seen.latencies_us.push(now.saturating_sub(h.msg.origin_ns) as f64 / 1e3);
                        seen.last_hop_us.push(now.saturating_sub(h.msg.publish_ns) as f64 / 1e3);
                    }
                    BURST => {
                        let start = *burst_start.get_or_insert(h.msg.origin_ns);
                        seen.burst_messages += 1;
                        seen.burst_s = now.saturating_sub(start) as f64 / 1e9;
                    }
                    _ => {}
                }
                last = Instant::now();
            }
            let done = seen.latencies_us.len() >= samples && seen.burst_messages >= burst;
            let stalled = last.elapsed() > Duration::from_secs(60);
            Ok::<_, StageError>(if done || stalled { Flow::Stop } else { Flow::Continue })
        })?;
        Ok(seen)
    });
    ready_rx.recv_timeout(Duration::from_secs(30)).context("the receiving runtime did not start")?;
    Ok(receiver)
}

/// Sends, in prefix `a`, 20 probes and `samples` timed clouds of `points` points at `rate_hz`,
/// then `burst` clouds as fast as the link takes them; returns what `receiver` saw (joined while
/// the publisher still lives, so that nothing in flight loses its sender).
fn send_row(
    a: &IoxScope,
    points: usize,
    cli: &Cli,
    burst: usize,
    receiver: std::thread::JoinHandle<anyhow::Result<Seen>>,
) -> anyhow::Result<Seen> {
    let options = RuntimeOptions { publish_control: false, ..Default::default() };
    let mut rt = Runtime::new("bench_tx", a, options)?;
    let qos = service_spec(CLOUD).context("cloud QoS")?.qos;
    let mut out = rt.output_slice_with_qos::<CloudPoint, CloudHeader>(
        CLOUD,
        &qos,
        points.max(1),
        Delivery::WaitWhenFull { max_wait: Some(Duration::from_secs(10)) },
    )?;
    // Until the sending bridge has subscribed (and waited for the other side to match).
    let t0 = Instant::now();
    while out.subscribers() == 0 {
        if t0.elapsed() > Duration::from_secs(30) {
            bail!("the sending bridge never subscribed");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let mut send = |flag: u8| -> anyhow::Result<usize> {
        let mut s = out.loan_slice_uninit(points)?.write_from_fn(|i| CloudPoint { x_m: i as f32, y_m: 0.0, z_m: 0.0 });
        *s.user_header_mut() = CloudHeader { msg: MsgHeader::default(), flags: flag as u32, ..Default::default() };
        Ok(out.send(s)?)
    };
    std::thread::sleep(Duration::from_secs(2));
    let period = Duration::from_secs_f64(1.0 / cli.rate_hz);
    for k in 0..20 + cli.samples {
        send(if k < 20 { PROBE } else { SAMPLE })?;
        std::thread::sleep(period);
    }
    for _ in 0..burst {
        send(BURST)?;
    }
    receiver.join().map_err(|_| anyhow::anyhow!("the receiver panicked"))?
}

/// The median of `v` (NaN when empty).
fn median(v: &[f64]) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    match s.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => s[n / 2],
        n => (s[n / 2 - 1] + s[n / 2]) / 2.0,
    }
}

fn pct(v: &[f64], q: f64) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    if s.is_empty() { f64::NAN } else { s[((s.len() - 1) as f64 * q).round() as usize] }
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    if let Some(ChildCommand::ZenohSub { listen, key, latency, burst }) = &cli.child {
        return zenoh_sub(listen, key, *latency, *burst);
    }
    let dir = tempfile::Builder::new().prefix("bridge-bench-").tempdir()?;
    println!(
        "bridge_bench: one-way latency in µs (one message in flight at {} Hz, {} measured per row) and throughput \
         (back to back, reliable), {} CPUs; bridge = iceoryx2 -> bridge -> Zenoh -> bridge -> iceoryx2",
        cli.rate_hz,
        cli.samples,
        std::thread::available_parallelism().map_or(0, |n| n.get())
    );
    let mut links: Vec<(String, Option<Shaped>)> = vec![("loopback".into(), None)];
    for (i, q) in cli.shape.iter().enumerate() {
        match Shaped::new(q, i) {
            Ok(sh) => links.push((format!("veth shaped by `tc qdisc ... {q}`"), Some(sh))),
            Err(e) => println!("link shaped by `{q}`: not measured: {e}"),
        }
    }
    let loopback = Net::loopback();
    let certs = make_certs(dir.path(), &links)?;
    for (l, (what, shaped)) in links.iter().enumerate() {
        let net = shaped.as_ref().map_or(&loopback, |s| &s.net);
        println!("link: {what}; bridge = plain TCP (insecure), tls = the bridge over mutual TLS");
        println!(
            "{:>9} | {:>9} {:>9} {:>8} | {:>10} {:>9} {:>8} {:>9} | {:>6} | {:>8} {:>9} {:>8} | {:>11} {:>9}",
            "bytes",
            "zenoh p50",
            "p99",
            "MB/s",
            "bridge p50",
            "p99",
            "MB/s",
            "last hop",
            "p50 x",
            "tls p50",
            "p99",
            "MB/s",
            "tls/tcp p50",
            "MB/s"
        );
        for (n, &size) in cli.sizes.iter().enumerate() {
            row(&cli, size, (l * 100 + n) * 100, dir.path(), net, &certs)?;
        }
    }
    Ok(())
}

/// Certificates for the TLS rows, made by `supervisor certs` (the addresses dialled in their SANs).
fn make_certs(dir: &std::path::Path, links: &[(String, Option<Shaped>)]) -> anyhow::Result<std::path::PathBuf> {
    let certs = dir.join("certs");
    let supervisor = std::env::current_exe()?.parent().context("bin dir")?.join("supervisor");
    let mut made = Command::new(&supervisor);
    made.args(["certs", "--days", "1", "--name", "r", "--name", "base", "--dir"]).arg(&certs);
    for sh in links.iter().filter_map(|(_, s)| s.as_ref()) {
        made.args(["--san", &sh.net.host]);
    }
    let out =
        made.output().with_context(|| format!("{} certs (build the workspace's binaries)", supervisor.display()))?;
    if !out.status.success() {
        bail!("supervisor certs: {}", String::from_utf8_lossy(&out.stderr));
    }
    Ok(certs)
}

/// One row of the table: bare Zenoh, then rounds of the bridge over TCP and over TLS.
fn row(
    cli: &Cli,
    size: usize,
    id0: usize,
    dir: &std::path::Path,
    net: &Net,
    certs: &std::path::Path,
) -> anyhow::Result<()> {
    let burst = (cli.burst_bytes / size.max(1)).clamp(20, 20_000);
    let z = bare(size, cli, burst, net)?;
    let mbs = |s: &Seen, bytes: usize| s.burst_messages as f64 * bytes as f64 / 1e6 / s.burst_s.max(1e-9);
    // Rounds of tcp then tls; the rows' columns pool the rounds, the ratios are per round.
    let (mut b, mut t, mut sent_size) = (Seen::default(), Seen::default(), size);
    let (mut p50_ratios, mut mbs_ratios) = (vec![], vec![]);
    for round in 0..cli.rounds.max(1) {
        let id = id0 + round;
        let (rb, sz) = bridged(size, cli, burst, dir, id, net, None)?;
        let (rt, _) = bridged(size, cli, burst, dir, id, net, Some(certs))?;
        sent_size = sz;
        p50_ratios.push(pct(&rt.latencies_us, 0.5) / pct(&rb.latencies_us, 0.5));
        mbs_ratios.push(mbs(&rt, sz) / mbs(&rb, sz));
        b.pool(rb);
        t.pool(rt);
    }
    println!(
        "{:>9} | {:>9.0} {:>9.0} {:>8.1} | {:>10.0} {:>9.0} {:>8.1} {:>9.0} | {:>6.2} | {:>8.0} {:>9.0} {:>8.1} | {:>11.2} {:>9.2}",
        size,
        pct(&z.latencies_us, 0.5),
        pct(&z.latencies_us, 0.99),
        mbs(&z, size),
        pct(&b.latencies_us, 0.5),
        pct(&b.latencies_us, 0.99),
        mbs(&b, sent_size),
        pct(&b.last_hop_us, 0.5),
        pct(&b.latencies_us, 0.5) / pct(&z.latencies_us, 0.5),
        pct(&t.latencies_us, 0.5),
        pct(&t.latencies_us, 0.99),
        mbs(&t, sent_size),
        median(&p50_ratios),
        median(&mbs_ratios)
    );
    if p50_ratios.len() > 1 {
        let range = |v: &[f64]| {
            let (lo, hi) = v.iter().fold((f64::MAX, f64::MIN), |(lo, hi), &x| (lo.min(x), hi.max(x)));
            format!("{lo:.2}-{hi:.2}")
        };
        println!(
            "          tls/tcp over {} rounds: p50 {}, MB/s {}",
            p50_ratios.len(),
            range(&p50_ratios),
            range(&mbs_ratios)
        );
    }
    let (samples, bursts) = (cli.samples * cli.rounds.max(1), burst * cli.rounds.max(1));
    if t.latencies_us.len() < samples || t.burst_messages < bursts {
        println!(
            "          note: the tls row got {} of {} latency and {} of {bursts} burst messages",
            t.latencies_us.len(),
            samples,
            t.burst_messages
        );
    }
    if b.latencies_us.len() < samples || b.burst_messages < bursts || sent_size != size {
        println!(
            "          note: the bridge row sent {sent_size}-byte clouds; got {} of {} latency and {} of \
             {bursts} burst messages",
            b.latencies_us.len(),
            samples,
            b.burst_messages
        );
    }
    if z.latencies_us.len() < cli.samples || z.burst_messages < burst {
        println!(
            "          note: the zenoh row got {} of {} latency and {} of {burst} burst messages",
            z.latencies_us.len(),
            cli.samples,
            z.burst_messages
        );
    }
    Ok(())
}
