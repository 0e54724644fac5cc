//! The relay role: one process of a chain. It receives link `index − 1`, records the hop's latency
//! (receive time − the sender's `publish_ns`), forwards the message on link `index` and, after the
//! [`END`] message, prints its report as one JSON line on stdout and exits.
//!
//! What a relay forwards: over iceoryx2 it loans a new sample of the same size, writes the header
//! and the 16 index bytes in place and sends (a zero-copy stage produces its output in place and
//! never copies its input; the rest of the payload is whatever the loaned chunk holds). Over a
//! socket it must copy: it reads the whole payload into its buffer and writes it on (bincode:
//! decodes and re-encodes it). Neither does any other work, so the difference is the transport's.
//!
//! Protocol on stdout (nothing else is printed there): [`READY_LINE`] once the relay's ports exist
//! (sockets: its input socket listens and its output is connected), then the report line.

use std::io::Write as _;
use std::os::unix::net::{UnixListener, UnixStream};
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail, ensure};
use pipeline_runtime::{Delivery, Flow, IoxScope, Runtime, RuntimeOptions, StopReason, monotonic_ns};
use serde::{Deserialize, Serialize};
use shared_types::{HasMsgHeader as _, MsgHeader};

use super::cli::{LatTransport, RelayArgs};
use super::links::{BareEndpoint, Bytes, link_qos, link_service, link_socket};
use super::wire::{
    BincodeMsg, END, RawHeader, assume_init_bytes, get_index, get_index_bytes, get_index_f32, put_index, read_bincode,
    read_raw, touch_bytes, write_bincode, write_raw,
};

/// The line a relay prints when it is ready.
pub const READY_LINE: &str = "READY";
/// Prefix of the relay's report line (followed by the JSON of a [`RelayReport`]).
pub const REPORT_PREFIX: &str = "REPORT ";
/// How long a relay waits for its upstream and downstream sockets to appear.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(30);

/// What a relay measured.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct RelayReport {
    /// Position in the chain.
    pub index: usize,
    /// Messages received, warm-up and end included.
    pub received: u64,
    /// Messages with a torn or wrong-size payload (not forwarded).
    pub bad: u64,
    /// Latency of the hop into this relay for each measured message, ns.
    pub hop_ns: Vec<u64>,
    /// WaitSet wake-ups with a notification (iceoryx2 transports; 0 for sockets).
    pub wakeups: u64,
}

/// Records what arrives at one receiver.
#[derive(Debug)]
pub struct HopRecorder {
    warmup: u64,
    size: usize,
    /// The report being built.
    pub report: RelayReport,
}

impl HopRecorder {
    /// A recorder for relay `index` that skips indices below `warmup` and expects `size` bytes.
    pub fn new(index: usize, warmup: u64, size: usize) -> Self {
        Self { warmup, size, report: RelayReport { index, ..Default::default() } }
    }

    /// Records one message: its index (`None` if torn), payload length, publish time, receive time.
    /// Returns the index to forward, or `None` for a bad message.
    pub fn record(&mut self, index: Option<u64>, len: usize, publish_ns: u64, now_ns: u64) -> Option<u64> {
        self.report.received += 1;
        let index = index.filter(|_| len == self.size);
        let Some(i) = index else {
            self.report.bad += 1;
            return None;
        };
        if i != END && i >= self.warmup && publish_ns > 0 && publish_ns <= now_ns {
            self.report.hop_ns.push(now_ns - publish_ns);
        }
        Some(i)
    }
}

fn say(line: &str) -> anyhow::Result<()> {
    let mut out = std::io::stdout().lock();
    writeln!(out, "{line}").and_then(|()| out.flush()).context("cannot write to the benchmark (stdout)")
}

/// Runs the relay role until the end message, then prints the report.
pub fn run_relay(args: &RelayArgs) -> anyhow::Result<()> {
    // Die with the benchmark even if it is SIGKILLed; exit if it is already gone.
    nix::sys::prctl::set_pdeathsig(nix::sys::signal::Signal::SIGKILL).context("prctl(PR_SET_PDEATHSIG)")?;
    ensure!(nix::unistd::getppid().as_raw() == args.parent_pid, "the benchmark (pid {}) is gone", args.parent_pid);
    ensure!(args.index >= 1, "--index starts at 1");
    let mut rec = HopRecorder::new(args.index, args.warmup, args.size);
    match args.transport {
        LatTransport::Iox => relay_iox(args, &mut rec)?,
        LatTransport::IoxBare => relay_iox_bare(args, &mut rec)?,
        LatTransport::SocketRaw | LatTransport::SocketBincode => relay_socket(args, &mut rec)?,
    }
    let json = serde_json::to_string(&rec.report).context("encoding the report")?;
    say(&format!("{REPORT_PREFIX}{json}"))
}

fn scope() -> anyhow::Result<IoxScope> {
    IoxScope::from_env().context("the iceoryx2 scope is not in the environment (started by pipeline_bench)")
}

fn relay_iox(args: &RelayArgs, rec: &mut HopRecorder) -> anyhow::Result<()> {
    let options = RuntimeOptions { publish_control: false, ..Default::default() };
    let mut rt = Runtime::new(&format!("lat_relay{}", args.index), &scope()?, options).context("relay runtime")?;
    let qos = link_qos(args.size);
    let input = rt.input_with_qos::<[Bytes], MsgHeader>(&link_service(&args.case, args.index - 1), &qos)?;
    let mut out = rt.output_slice_with_qos::<Bytes, MsgHeader>(
        &link_service(&args.case, args.index),
        &qos,
        args.size,
        Delivery::DiscardWhenFull,
    )?;
    say(READY_LINE)?;
    let reason = rt.run(rec, None, |_rt, rec, wake| {
        rec.report.wakeups += u64::from(wake.data);
        while let Some(sample) = input.receive()? {
            let now = monotonic_ns();
            let h = *sample.user_header().msg();
            let payload = sample.payload();
            let now = touch_input(args.touch, payload, now);
            let Some(index) = rec.record(get_index(payload), payload.len(), h.publish_ns, now) else { continue };
            let loaned = out.loan_slice_uninit(payload.len())?;
            // SAFETY: the payload type is `MaybeUninit<u8>`: any bytes are a valid value.
            let mut o = unsafe { loaned.assume_init() };
            if args.touch {
                o.payload_mut().copy_from_slice(payload);
            }
            put_index(o.payload_mut(), index);
            *o.user_header_mut() = MsgHeader { stamp_ns: h.stamp_ns, origin_ns: h.origin_ns, ..Default::default() };
            drop(sample);
            out.send(o)?;
            if index == END {
                return Ok::<_, anyhow::Error>(Flow::Stop);
            }
        }
        Ok(Flow::Continue)
    })?;
    if let StopReason::Signal(sig) = reason {
        bail!("stopped by signal {sig} before the end message");
    }
    Ok(())
}

fn relay_iox_bare(args: &RelayArgs, rec: &mut HopRecorder) -> anyhow::Result<()> {
    let ep = BareEndpoint::new(
        &scope()?,
        &format!("lat_bare{}", args.index),
        &link_service(&args.case, args.index - 1),
        &link_service(&args.case, args.index),
        args.size,
    )?;
    say(READY_LINE)?;
    let idle = Duration::from_secs(1);
    ep.run(idle, |woke| {
        rec.report.wakeups += u64::from(woke);
        while let Some(sample) = ep.receive()? {
            let now = monotonic_ns();
            let h = *sample.user_header();
            let payload = sample.payload();
            let now = touch_input(args.touch, payload, now);
            let Some(index) = rec.record(get_index(payload), payload.len(), h.publish_ns, now) else { continue };
            let mut o = ep.loan(payload.len())?;
            if args.touch {
                o.payload_mut().copy_from_slice(payload);
            }
            put_index(o.payload_mut(), index);
            *o.user_header_mut() =
                MsgHeader { stamp_ns: h.stamp_ns, origin_ns: h.origin_ns, publish_ns: monotonic_ns(), seq: h.seq };
            drop(sample);
            ep.send(o)?;
            if index == END {
                return Ok(None);
            }
        }
        Ok(Some(idle))
    })
}

/// The receive time after reading every byte of `payload` when `touch` is set; else `now`.
/// Under `--touch` every sender wrote the whole payload, so every byte is initialised.
pub fn touch_input(touch: bool, payload: &[super::links::Bytes], now: u64) -> u64 {
    if !touch {
        return now;
    }
    // SAFETY: under `--touch` the producer and every relay write the whole payload.
    touched(touch_bytes(unsafe { assume_init_bytes(payload) }))
}

/// The time after a read pass whose result is `sum` (kept so that the pass is not optimised away).
pub fn touched(sum: u64) -> u64 {
    std::hint::black_box(sum);
    monotonic_ns()
}

/// Connects to a socket that another process is about to create.
pub fn connect_within(path: &std::path::Path, timeout: Duration) -> anyhow::Result<UnixStream> {
    let end = Instant::now() + timeout;
    loop {
        match UnixStream::connect(path) {
            Ok(s) => return Ok(s),
            Err(e)
                if Instant::now() < end
                    && matches!(e.kind(), std::io::ErrorKind::NotFound | std::io::ErrorKind::ConnectionRefused) =>
            {
                std::thread::sleep(Duration::from_millis(5));
            }
            Err(e) => return Err(e).with_context(|| format!("connecting to {}", path.display())),
        }
    }
}

fn relay_socket(args: &RelayArgs, rec: &mut HopRecorder) -> anyhow::Result<()> {
    let dir = args.socket_dir.as_ref().context("--socket-dir is required for the socket transports")?;
    let in_path = link_socket(dir, &args.case, args.index - 1);
    let listener = UnixListener::bind(&in_path).with_context(|| format!("cannot listen on {}", in_path.display()))?;
    let mut out = connect_within(&link_socket(dir, &args.case, args.index), CONNECT_TIMEOUT)?;
    say(READY_LINE)?;
    let (mut input, _) = listener.accept().context("accepting the upstream connection")?;
    // A stalled chain must not hang the relay forever (the benchmark also kills it on drop).
    input.set_read_timeout(Some(Duration::from_secs(120))).context("setting the read timeout")?;
    let mut buf = Vec::new();
    if args.transport == LatTransport::SocketRaw {
        loop {
            let h = read_raw(&mut input, &mut buf, args.size)?;
            let now = if args.touch { touched(touch_bytes(&buf)) } else { monotonic_ns() };
            let Some(index) = rec.record(get_index_bytes(&buf), buf.len(), h.publish_ns, now) else { continue };
            let header = RawHeader { index, origin_ns: h.origin_ns, publish_ns: monotonic_ns(), len: buf.len() as u64 };
            write_raw(&mut out, header, &buf)?;
            if index == END {
                return Ok(());
            }
        }
    }
    let mut enc = Vec::new();
    loop {
        let mut msg: BincodeMsg = read_bincode(&mut input, &mut buf, args.size)?;
        let now = if args.touch {
            touched(msg.payload.iter().fold(0u32, |a, v| a.wrapping_add(v.to_bits())).into())
        } else {
            monotonic_ns()
        };
        let got = get_index_f32(&msg.payload).filter(|&i| i == msg.index);
        let Some(index) = rec.record(got, msg.payload.len() * 4, msg.publish_ns, now) else { continue };
        msg.publish_ns = monotonic_ns();
        write_bincode(&mut out, &msg, &mut enc)?;
        if index == END {
            return Ok(());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_recorder_skips_warmup_and_end_and_rejects_torn_or_wrong_size_messages() {
        let mut r = HopRecorder::new(1, 2, 64);
        assert_eq!(r.record(Some(0), 64, 10, 20), Some(0));
        assert_eq!(r.record(Some(2), 64, 10, 25), Some(2));
        assert_eq!(r.record(Some(3), 32, 10, 25), None, "wrong size");
        assert_eq!(r.record(None, 64, 10, 25), None, "torn");
        assert_eq!(r.record(Some(END), 64, 10, 25), Some(END));
        assert_eq!(r.report.hop_ns, vec![15]);
        assert_eq!((r.report.received, r.report.bad), (5, 2));
    }
}
