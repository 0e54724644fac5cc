//! The consumer role: the child process that receives every cloud of one transport, reads every
//! point, records latency and CPU per cloud, and reports the raw samples to the parent as one JSON
//! line on stdout ([`REPORT_PREFIX`]) after the producer's end of stream.
//!
//! Protocol on stdout (nothing else is printed there): [`READY_LINE`] once the consumer can receive
//! (iceoryx2: subscriber and listener exist; sockets: connected), then the report line.

use std::io::{Read, Write};
use std::os::unix::net::UnixStream;
use std::time::Duration;

use anyhow::{Context as _, bail};
use pipeline_runtime::{Flow, IoxScope, Runtime, RuntimeOptions, StopReason, monotonic_ns};
use serde::{Deserialize, Serialize};
use shared_types::services::{CLOUD, END_OF_STREAM};
use shared_types::{CloudHeader, CloudPoint, EndOfStream, MsgHeader};

use crate::cli::{ConsumerArgs, Transport};
use crate::content::{
    BincodeCloud, RAW_END, RawHeader, bincode_config, checksum_points, checksum_xyz, spot_check, xyz_as_bytes_mut,
};
use crate::cpu::thread_cpu_ns;

/// The line a consumer prints when it is ready to receive.
pub const READY_LINE: &str = "READY";
/// Prefix of the consumer's report line (followed by the JSON of a [`ConsumerReport`]).
pub const REPORT_PREFIX: &str = "REPORT ";

/// What a consumer measured; the per-cloud vectors hold only clouds with `seq >= warmup`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ConsumerReport {
    /// Transport name.
    pub transport: String,
    /// Clouds received, warm-up included.
    pub received: u64,
    /// Clouds missing in the sequence (overwritten or dropped before they were received).
    pub seq_gaps: u64,
    /// Clouds that failed the size/content spot check.
    pub bad_frames: u64,
    /// Clouds whose publish time was zero or in the future (not recorded).
    pub bad_stamps: u64,
    /// Checksum of all points of all clouds (wrapping sum of the per-cloud checksums).
    pub checksum: u32,
    /// Hop latency per cloud: consumer has read every point − publish time, ns.
    pub latency_ns: Vec<u64>,
    /// Ready latency per cloud: payload usable (before the read pass) − publish time, ns.
    pub ready_ns: Vec<u64>,
    /// Consumer thread CPU per cloud (receive, deserialise, read), ns.
    pub cpu_ns: Vec<u64>,
}

/// Accumulates one consumer's measurements.
#[derive(Debug)]
struct Recorder {
    report: ConsumerReport,
    warmup: u64,
    points: usize,
    last_seq: Option<u64>,
}

/// One received cloud's measurements.
struct Received {
    seq: u64,
    publish_ns: u64,
    ready_at_ns: u64,
    read_at_ns: u64,
    cpu_ns: u64,
    checksum: u32,
    ok: bool,
}

impl Recorder {
    fn new(transport: Transport, warmup: u64, points: usize) -> Self {
        Self {
            report: ConsumerReport { transport: transport.name().into(), ..Default::default() },
            warmup,
            points,
            last_seq: None,
        }
    }

    fn record(&mut self, r: Received) {
        let rep = &mut self.report;
        rep.received += 1;
        if let Some(last) = self.last_seq
            && r.seq > last + 1
        {
            rep.seq_gaps += r.seq - last - 1;
        }
        self.last_seq = Some(r.seq);
        rep.checksum = rep.checksum.wrapping_add(r.checksum);
        if !r.ok {
            rep.bad_frames += 1;
        }
        if r.seq < self.warmup {
            return;
        }
        if r.publish_ns == 0 || r.publish_ns > r.ready_at_ns {
            rep.bad_stamps += 1;
            return;
        }
        rep.latency_ns.push(r.read_at_ns - r.publish_ns);
        rep.ready_ns.push(r.ready_at_ns - r.publish_ns);
        rep.cpu_ns.push(r.cpu_ns);
    }
}

fn say(line: &str) -> anyhow::Result<()> {
    let mut out = std::io::stdout().lock();
    writeln!(out, "{line}").and_then(|()| out.flush()).context("cannot write to the parent (stdout)")
}

/// Runs the consumer role until the producer's end of stream, then prints the report.
pub fn run_consumer(args: &ConsumerArgs) -> anyhow::Result<()> {
    // Die with the benchmark even if it is SIGKILLed; exit if it is already gone.
    nix::sys::prctl::set_pdeathsig(nix::sys::signal::Signal::SIGKILL).context("prctl(PR_SET_PDEATHSIG)")?;
    if nix::unistd::getppid().as_raw() != args.parent_pid {
        bail!("the benchmark (pid {}) is gone", args.parent_pid);
    }
    let mut rec = Recorder::new(args.transport, args.warmup, args.points);
    match args.transport {
        Transport::Iox => consume_iox(&mut rec)?,
        Transport::SocketBincode => consume_bincode(&mut rec, &connect(args)?)?,
        Transport::SocketRaw => consume_raw(&mut rec, &connect(args)?)?,
    }
    let json = serde_json::to_string(&rec.report).context("encoding the report")?;
    say(&format!("{REPORT_PREFIX}{json}"))
}

fn consume_iox(rec: &mut Recorder) -> anyhow::Result<()> {
    let scope = IoxScope::from_env().context("the iceoryx2 scope is not in the environment (run by ingest_bench)")?;
    let options = RuntimeOptions { publish_control: false, ..Default::default() };
    let mut rt = Runtime::new("bench_consumer", &scope, options).context("creating the consumer's runtime")?;
    let clouds = rt.input::<[CloudPoint], CloudHeader>(CLOUD).context("opening the cloud input")?;
    let eos = rt.input::<EndOfStream, MsgHeader>(END_OF_STREAM).context("opening the end-of-stream input")?;
    say(READY_LINE)?;
    let reason = rt.run(rec, None, |_rt, rec, _wake| {
        loop {
            let cpu0 = thread_cpu_ns();
            let Some(sample) = clouds.receive()? else { break };
            let ready_at_ns = monotonic_ns();
            let h = sample.user_header().msg;
            let points = sample.payload();
            let checksum = checksum_points(points);
            let ok = spot_check(h.seq, rec.points, points.len(), |i| {
                let p = points[i];
                [p.x_m, p.y_m, p.z_m]
            });
            let read_at_ns = monotonic_ns();
            drop(sample);
            let cpu_ns = thread_cpu_ns() - cpu0;
            rec.record(Received {
                seq: h.seq,
                publish_ns: h.publish_ns,
                ready_at_ns,
                read_at_ns,
                cpu_ns,
                checksum,
                ok,
            });
        }
        Ok::<_, anyhow::Error>(if eos.receive()?.is_some() { Flow::Stop } else { Flow::Continue })
    })?;
    if let StopReason::Signal(sig) = reason {
        bail!("stopped by signal {sig} before the end of stream");
    }
    Ok(())
}

fn connect(args: &ConsumerArgs) -> anyhow::Result<UnixStream> {
    let path = args.socket.as_ref().context("--socket is required for the socket transports")?;
    let stream = UnixStream::connect(path).with_context(|| format!("connecting to {}", path.display()))?;
    // A stalled producer must not hang the consumer forever (the parent also kills it on drop).
    stream.set_read_timeout(Some(Duration::from_secs(60))).context("setting the read timeout")?;
    say(READY_LINE)?;
    Ok(stream)
}

fn read_u64(stream: &mut &UnixStream) -> anyhow::Result<u64> {
    let mut b = [0u8; 8];
    stream.read_exact(&mut b).context("reading a frame length")?;
    Ok(u64::from_le_bytes(b))
}

fn consume_bincode(rec: &mut Recorder, stream: &UnixStream) -> anyhow::Result<()> {
    let mut stream = stream;
    let mut buf = Vec::new();
    loop {
        let cpu0 = thread_cpu_ns();
        let len = read_u64(&mut stream)?;
        if len == 0 {
            return Ok(());
        }
        let len = usize::try_from(len).context("frame length")?;
        buf.resize(len, 0);
        stream.read_exact(&mut buf).context("reading a bincode frame")?;
        let (cloud, _): (BincodeCloud, usize) =
            bincode::serde::decode_from_slice(&buf, bincode_config()).context("decoding a bincode frame")?;
        let ready_at_ns = monotonic_ns();
        let h = cloud.header;
        let checksum = checksum_xyz(&cloud.points);
        let ok = spot_check(h.seq, rec.points, cloud.points.len(), |i| cloud.points[i]);
        let read_at_ns = monotonic_ns();
        drop(cloud);
        let cpu_ns = thread_cpu_ns() - cpu0;
        rec.record(Received { seq: h.seq, publish_ns: h.publish_ns, ready_at_ns, read_at_ns, cpu_ns, checksum, ok });
    }
}

fn consume_raw(rec: &mut Recorder, stream: &UnixStream) -> anyhow::Result<()> {
    let mut stream = stream;
    let mut points: Vec<[f32; 3]> = Vec::new();
    loop {
        let cpu0 = thread_cpu_ns();
        let mut hb = [0u8; RawHeader::SIZE];
        stream.read_exact(&mut hb).context("reading a raw frame header")?;
        let h = RawHeader::from_bytes(&hb);
        if h.points == RAW_END {
            return Ok(());
        }
        let n = usize::try_from(h.points).ok().filter(|&n| n <= crate::cli::MAX_POINTS).context("raw frame size")?;
        points.resize(n, [0.0; 3]);
        stream.read_exact(xyz_as_bytes_mut(&mut points)).context("reading raw points")?;
        let ready_at_ns = monotonic_ns();
        let checksum = checksum_xyz(&points);
        let ok = spot_check(h.seq, rec.points, points.len(), |i| points[i]);
        let read_at_ns = monotonic_ns();
        let cpu_ns = thread_cpu_ns() - cpu0;
        rec.record(Received { seq: h.seq, publish_ns: h.publish_ns, ready_at_ns, read_at_ns, cpu_ns, checksum, ok });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rx(seq: u64, publish_ns: u64) -> Received {
        Received {
            seq,
            publish_ns,
            ready_at_ns: publish_ns + 10,
            read_at_ns: publish_ns + 30,
            cpu_ns: 5,
            checksum: 1,
            ok: true,
        }
    }

    #[test]
    fn recorder_skips_warmup_counts_gaps_and_rejects_bad_stamps() {
        let mut r = Recorder::new(Transport::Iox, 2, 10);
        for seq in [0, 1, 2, 5] {
            r.record(rx(seq, 1000));
        }
        r.record(Received { ready_at_ns: 5, ..rx(6, 1000) }); // published "after" it was ready
        let rep = &r.report;
        assert_eq!(rep.received, 5);
        assert_eq!(rep.seq_gaps, 2);
        assert_eq!(rep.bad_stamps, 1);
        assert_eq!(rep.latency_ns, vec![30, 30]);
        assert_eq!(rep.ready_ns, vec![10, 10]);
        assert_eq!(rep.checksum, 5);
    }
}
