//! The benchmark run: an isolated iceoryx2 scope (prefix `lat<pid>_`, root under a temporary
//! directory, every file removed at the end), then one case per payload size × chain length ×
//! transport, each with fresh relay processes, the producer in this process.

use std::os::unix::net::{UnixListener, UnixStream};
use std::path::Path;
use std::process::Command;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail, ensure};
use pipeline_runtime::{Delivery, Flow, IoxScope, Runtime, RuntimeOptions, StopReason, monotonic_ns};
use shared_types::{HasMsgHeader as _, MsgHeader};

use super::cli::{LatTransport, LatencyArgs, size_label};
use super::links::{BareEndpoint, Bytes, link_qos, link_service, link_socket};
use super::pacer::{Action, Pacer};
use super::relay::{READY_LINE, REPORT_PREFIX, RelayReport, connect_within, touch_input, touched};
use super::report::{CaseResult, LatencyResult};
use super::wire::{
    BincodeMsg, RawHeader, fill_pattern, get_index, get_index_bytes, get_index_f32, put_index, put_index_bytes,
    put_index_f32, read_bincode, read_raw, touch_bytes, write_bincode, write_raw,
};
use crate::bench::{ScopeCleanup, accept_within};
use crate::child::ConsumerProcess;
use crate::report::Summary;

/// How long a relay may take to start.
const READY_TIMEOUT: Duration = Duration::from_secs(30);

/// One case: which transport, payload and chain.
#[derive(Debug, Clone, Copy)]
struct Case {
    transport: LatTransport,
    size: usize,
    chain: usize,
}

impl Case {
    fn name(&self) -> String {
        format!("{}-{}-c{}", self.transport.name(), self.size, self.chain)
    }
}

/// Runs every case of `args`; progress goes to stderr.
pub fn run_latency(args: &LatencyArgs) -> anyhow::Result<LatencyResult> {
    args.validate()?;
    let dir = tempfile::Builder::new().prefix("pipeline_bench-").tempdir().context("creating a temporary directory")?;
    let scope =
        IoxScope { prefix: format!("lat{}_", std::process::id()), root: dir.path().join("iox"), base_config: None };
    let cleanup = ScopeCleanup { scope: scope.clone() };
    let interrupted = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(sig, interrupted.clone()).context("installing the signal handlers")?;
    }
    let mut result = LatencyResult { prefix: scope.prefix.clone(), ..Default::default() };
    let total = args.sizes.len() * args.chains.len() * args.transports.len();
    let mut done = 0;
    for &size in &args.sizes {
        for &chain in &args.chains {
            for &transport in &args.transports {
                done += 1;
                let case = Case { transport, size, chain };
                eprintln!(
                    "pipeline_bench: [{done}/{total}] {} {} through {chain} relay(s): {} + {} messages at {} Hz",
                    transport.name(),
                    size_label(size),
                    args.warmup,
                    args.samples,
                    args.rate_hz
                );
                let r = run_case(args, &scope, dir.path(), case, &interrupted)
                    .with_context(|| format!("case {} {} chain {chain}", transport.name(), size_label(size)))?;
                result.cases.push(r);
            }
        }
    }
    cleanup.finish()?;
    Ok(result)
}

fn spawn_relay(
    args: &LatencyArgs,
    scope: &IoxScope,
    dir: &Path,
    case: Case,
    index: usize,
) -> anyhow::Result<ConsumerProcess> {
    let exe = std::env::current_exe().context("cannot find this executable to start the relays")?;
    let mut cmd = Command::new(exe);
    cmd.arg("relay")
        .args(["--transport", case.transport.name()])
        .args(["--index", &index.to_string()])
        .args(["--case", &case.name()])
        .args(["--size", &case.size.to_string()])
        .args(["--warmup", &args.warmup.to_string()])
        .args(["--parent-pid", &std::process::id().to_string()])
        .args(args.touch.then_some("--touch"))
        .arg("--socket-dir")
        .arg(dir);
    scope.export_to(&mut cmd);
    ConsumerProcess::spawn_command(cmd, format!("relay {index} ({})", case.transport.name()))
}

fn run_case(
    args: &LatencyArgs,
    scope: &IoxScope,
    dir: &Path,
    case: Case,
    interrupted: &AtomicBool,
) -> anyhow::Result<CaseResult> {
    let cancel = || interrupted.load(Ordering::Relaxed).then_some(2);
    // The socket the last relay connects to must exist before it starts.
    let return_listener = if case.transport.is_iox() {
        None
    } else {
        let path = link_socket(dir, &case.name(), case.chain);
        Some(UnixListener::bind(&path).with_context(|| format!("cannot listen on {}", path.display()))?)
    };
    // Downstream first: each relay connects its output to the next one's input.
    let mut relays = Vec::with_capacity(case.chain);
    for index in (1..=case.chain).rev() {
        let mut relay = spawn_relay(args, scope, dir, case, index)?;
        relay.wait_line(READY_LINE, READY_TIMEOUT, &cancel)?;
        relays.push(relay);
    }
    relays.reverse();
    let timeout = Duration::from_millis(args.timeout_ms);
    let mut pacer =
        Pacer::new(args.warmup, args.samples, args.rate_hz, timeout, Duration::from_secs_f64(args.max_case_seconds));
    match case.transport {
        LatTransport::Iox => drive_iox(scope, case, args.touch, &mut pacer)?,
        LatTransport::IoxBare => drive_iox_bare(scope, case, args.touch, &mut pacer, interrupted)?,
        LatTransport::SocketRaw | LatTransport::SocketBincode => {
            let mut out = connect_within(&link_socket(dir, &case.name(), 0), READY_TIMEOUT)?;
            let mut input = accept_within(return_listener.as_ref().context("no return listener")?, READY_TIMEOUT)?;
            input.set_read_timeout(Some(timeout)).context("setting the read timeout")?;
            drive_socket(case, args.touch, &mut out, &mut input, &mut pacer, interrupted)?;
        }
    }
    let mut reports = Vec::with_capacity(case.chain);
    for relay in &mut relays {
        let json = relay.wait_line(REPORT_PREFIX, Duration::from_secs(60), &cancel)?;
        let report: RelayReport = serde_json::from_str(&json).context("malformed relay report")?;
        let status = relay.wait_exit(Duration::from_secs(10))?;
        ensure!(status.success(), "relay {} exited with {status}", report.index);
        reports.push(report);
    }
    let mut hops: Vec<Option<Summary>> = reports.iter().map(|r| Summary::of(&r.hop_ns)).collect();
    hops.push(Summary::of(&pacer.last_hop_ns));
    let relayed: u64 = reports.iter().map(|r| r.received).sum();
    let wakeups: u64 = reports.iter().map(|r| r.wakeups).sum();
    let bad = pacer.bad + reports.iter().map(|r| r.bad).sum::<u64>();
    let r = CaseResult {
        transport: case.transport.name().to_string(),
        size_bytes: case.size,
        chain: case.chain,
        hops,
        e2e: Summary::of(&pacer.e2e_ns),
        e2e_ns: std::mem::take(&mut pacer.e2e_ns),
        samples_wanted: args.samples,
        lost: pacer.lost,
        bad,
        late: pacer.late,
        cut_short: pacer.cut_short,
        wakeups_per_message: (case.transport.is_iox() && relayed > 0).then(|| wakeups as f64 / relayed as f64),
    };
    if let Some(e) = r.e2e {
        eprintln!(
            "pipeline_bench:   end to end p50 {:.1} µs, p99 {:.1} µs ({} samples)",
            e.p50 as f64 / 1e3,
            e.p99 as f64 / 1e3,
            e.count
        );
    }
    Ok(r)
}

/// Reads every value of a bincode payload (`--touch`).
fn f32_sum(v: &[f32]) -> u64 {
    v.iter().fold(0u32, |a, x| a.wrapping_add(x.to_bits())).into()
}

/// Fills a loaned iceoryx2 payload with the producer's pattern and index (not timed).
fn fill_uninit(payload: &mut [Bytes], index: u64, scratch: &mut Vec<u8>) {
    if scratch.len() != payload.len() {
        scratch.resize(payload.len(), 0);
        fill_pattern(scratch, 1);
    }
    for (d, s) in payload.iter_mut().zip(scratch.iter()) {
        d.write(*s);
    }
    put_index(payload, index);
}

fn drive_iox(scope: &IoxScope, case: Case, touch: bool, pacer: &mut Pacer) -> anyhow::Result<()> {
    let options = RuntimeOptions { publish_control: false, ..Default::default() };
    let mut rt = Runtime::new("lat_producer", scope, options).context("producer runtime")?;
    let qos = link_qos(case.size);
    let name = case.name();
    let mut out = rt.output_slice_with_qos::<Bytes, MsgHeader>(
        &link_service(&name, 0),
        &qos,
        case.size,
        Delivery::DiscardWhenFull,
    )?;
    let input = rt.input_with_qos::<[Bytes], MsgHeader>(&link_service(&name, case.chain), &qos)?;
    let mut scratch = Vec::new();
    rt.wake_at(Instant::now());
    let reason = rt.run(pacer, None, |rt, p, _wake| {
        while let Some(s) = input.receive()? {
            let now = touch_input(touch, s.payload(), monotonic_ns());
            let h = *s.user_header().msg();
            let index = get_index(s.payload()).filter(|_| s.payload().len() == case.size);
            p.received(index, h.origin_ns, h.publish_ns, now);
        }
        loop {
            match p.next_action(Instant::now())? {
                Action::Done => return Ok::<_, anyhow::Error>(Flow::Stop),
                Action::WaitUntil(t) => {
                    rt.wake_at(t);
                    return Ok(Flow::Continue);
                }
                Action::Send(i) => {
                    let loaned = out.loan_slice_uninit(case.size)?;
                    // SAFETY: the payload type is `MaybeUninit<u8>`: any bytes are a valid value.
                    let mut o = unsafe { loaned.assume_init() };
                    fill_uninit(o.payload_mut(), i, &mut scratch);
                    *o.user_header_mut() = MsgHeader::default(); // send stamps origin = publish time
                    let at = Instant::now();
                    out.send(o)?;
                    p.sent(i, at);
                }
            }
        }
    })?;
    if let StopReason::Signal(sig) = reason {
        bail!("interrupted by signal {sig}");
    }
    Ok(())
}

fn drive_iox_bare(
    scope: &IoxScope,
    case: Case,
    touch: bool,
    pacer: &mut Pacer,
    interrupted: &AtomicBool,
) -> anyhow::Result<()> {
    let name = case.name();
    let ep = BareEndpoint::new(
        scope,
        "lat_bare_producer",
        &link_service(&name, case.chain),
        &link_service(&name, 0),
        case.size,
    )?;
    let mut scratch = Vec::new();
    ep.run(Duration::ZERO, |_woke| {
        if interrupted.load(Ordering::Relaxed) {
            bail!("interrupted by a signal");
        }
        while let Some(s) = ep.receive()? {
            let now = touch_input(touch, s.payload(), monotonic_ns());
            let h = *s.user_header();
            let index = get_index(s.payload()).filter(|_| s.payload().len() == case.size);
            pacer.received(index, h.origin_ns, h.publish_ns, now);
        }
        loop {
            match pacer.next_action(Instant::now())? {
                Action::Done => return Ok(None),
                Action::WaitUntil(t) => {
                    // Wake at least once a second to notice a signal.
                    return Ok(Some(t.saturating_duration_since(Instant::now()).min(Duration::from_secs(1))));
                }
                Action::Send(i) => {
                    let mut o = ep.loan(case.size)?;
                    fill_uninit(o.payload_mut(), i, &mut scratch);
                    let at = Instant::now();
                    let ns = monotonic_ns();
                    *o.user_header_mut() = MsgHeader { stamp_ns: ns, seq: i, origin_ns: ns, publish_ns: ns };
                    ep.send(o)?;
                    pacer.sent(i, at);
                }
            }
        }
    })
}

fn drive_socket(
    case: Case,
    touch: bool,
    out: &mut UnixStream,
    input: &mut UnixStream,
    pacer: &mut Pacer,
    interrupted: &AtomicBool,
) -> anyhow::Result<()> {
    let raw = case.transport == LatTransport::SocketRaw;
    let mut payload = vec![0u8; case.size];
    fill_pattern(&mut payload, 1);
    let mut msg = BincodeMsg {
        payload: payload.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect(),
        ..Default::default()
    };
    let (mut buf, mut enc) = (Vec::new(), Vec::new());
    loop {
        if interrupted.load(Ordering::Relaxed) {
            bail!("interrupted by a signal");
        }
        match pacer.next_action(Instant::now())? {
            Action::Done => return Ok(()),
            Action::WaitUntil(t) if pacer.in_flight().is_none() => {
                std::thread::sleep(t.saturating_duration_since(Instant::now()).min(Duration::from_secs(1)));
            }
            // A socket loses nothing: the reply comes, or the chain is broken (read timeout).
            Action::WaitUntil(_) if raw => {
                let h = read_raw(input, &mut buf, case.size).context("waiting for the reply")?;
                let now = if touch { touched(touch_bytes(&buf)) } else { monotonic_ns() };
                let index = get_index_bytes(&buf).filter(|&i| i == h.index && buf.len() == case.size);
                pacer.received(index, h.origin_ns, h.publish_ns, now);
            }
            Action::WaitUntil(_) => {
                let m = read_bincode(input, &mut buf, case.size).context("waiting for the reply")?;
                let now = if touch { touched(f32_sum(&m.payload)) } else { monotonic_ns() };
                let index = get_index_f32(&m.payload).filter(|&i| i == m.index && m.payload.len() * 4 == case.size);
                pacer.received(index, m.origin_ns, m.publish_ns, now);
            }
            Action::Send(i) => {
                let at = Instant::now();
                if raw {
                    put_index_bytes(&mut payload, i);
                    let ns = monotonic_ns();
                    write_raw(
                        out,
                        RawHeader { index: i, origin_ns: ns, publish_ns: ns, len: case.size as u64 },
                        &payload,
                    )?;
                } else {
                    put_index_f32(&mut msg.payload, i);
                    msg.index = i;
                    msg.origin_ns = monotonic_ns();
                    msg.publish_ns = msg.origin_ns;
                    write_bincode(out, &msg, &mut enc)?;
                }
                pacer.sent(i, at);
            }
        }
    }
}
