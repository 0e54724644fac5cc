//! The benchmark run: an isolated iceoryx2 scope (unique prefix, root under a temporary directory,
//! every file removed at the end), the `gen-only` reference, then one producer/consumer phase per
//! transport with a fresh consumer child each, and the rows of the table.

use std::os::unix::net::{UnixListener, UnixStream};
use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail, ensure};
use pipeline_runtime::{Delivery, IoxScope, Runtime, RuntimeOptions};
use shared_types::services::{CLOUD, service_spec};
use shared_types::{CloudHeader, CloudPoint};

use crate::child::ConsumerProcess;
use crate::cli::{BenchArgs, Transport};
use crate::consumer::{ConsumerReport, READY_LINE, REPORT_PREFIX};
use crate::content::{bench_xyz, checksum_xyz};
use crate::producer::{Driven, FrameSink, GenOnlySink, IoxSink, Pacing, SocketBincodeSink, SocketRawSink, drive};
use crate::report::{GEN_ONLY, Row, Summary};

/// The iceoryx2 Delivery of the benchmark's cloud publisher. The cloud service of the contract
/// overflows (newest wins), so the publisher never blocks whichever Delivery is chosen; this is the
/// one a live ingest uses.
pub const IOX_DELIVERY: Delivery = Delivery::DiscardWhenFull;

/// How long a consumer may take to start (create its node and ports, or connect).
const READY_TIMEOUT: Duration = Duration::from_secs(30);

/// Results of a run.
#[derive(Debug, Clone, Default)]
pub struct BenchResult {
    /// One row per transport, `gen-only` first.
    pub rows: Vec<Row>,
    /// Things worth knowing about the run (late clouds, lost clouds, undelivered sends).
    pub notes: Vec<String>,
    /// The iceoryx2 prefix the run used (nothing with it is left in /dev/shm).
    pub prefix: String,
    /// Transports whose checksum over every point of every cloud matched the producer's content.
    pub verified: Vec<String>,
}

/// Removes the scope's files when dropped (also on errors, after the children are gone).
pub(crate) struct ScopeCleanup {
    /// The benchmark's iceoryx2 scope.
    pub(crate) scope: IoxScope,
}

impl ScopeCleanup {
    /// Removes every file of the scope and checks that /dev/shm holds none any more.
    pub(crate) fn finish(self) -> anyhow::Result<()> {
        self.scope.remove_all_resources().context("removing the benchmark's iceoryx2 files")?;
        let left = self.scope.shm_files();
        ensure!(left.is_empty(), "iceoryx2 files left in /dev/shm: {left:?}");
        Ok(())
    }
}

impl Drop for ScopeCleanup {
    fn drop(&mut self) {
        let _ = self.scope.remove_all_resources();
    }
}

/// Runs the whole benchmark (`gen-only`, then every transport of `args`).
pub fn run_bench(args: &BenchArgs) -> anyhow::Result<BenchResult> {
    args.validate()?;
    let dir =
        tempfile::Builder::new().prefix("ingest_bench-").tempdir().context("cannot create a temporary directory")?;
    let scope =
        IoxScope { prefix: format!("bench{}_", std::process::id()), root: dir.path().join("iox"), base_config: None };
    let cleanup = ScopeCleanup { scope: scope.clone() };
    let mut result = BenchResult { prefix: scope.prefix.clone(), ..Default::default() };
    {
        let options = RuntimeOptions { publish_control: false, ..Default::default() };
        let mut rt = Runtime::new("bench_producer", &scope, options).context("creating the producer's runtime")?;
        measure_all(&mut rt, args, &scope, dir.path(), &mut result)?;
    }
    cleanup.finish()?;
    Ok(result)
}

fn pacing(args: &BenchArgs) -> Pacing {
    Pacing { warmup: args.warmup, frames: args.frames, period: Duration::from_secs_f64(1.0 / args.rate_hz) }
}

fn announce(args: &BenchArgs, name: &str) {
    let secs = args.total_frames() as f64 / args.rate_hz;
    eprintln!("ingest_bench: {name}: {} clouds at {} Hz (~{secs:.1} s)", args.total_frames(), args.rate_hz);
}

fn measure_all(
    rt: &mut Runtime,
    args: &BenchArgs,
    scope: &IoxScope,
    dir: &Path,
    result: &mut BenchResult,
) -> anyhow::Result<()> {
    announce(args, GEN_ONLY);
    let driven = drive(rt, &mut GenOnlySink::new(args.points), pacing(args)).context("gen-only")?;
    note_late(&mut result.notes, GEN_ONLY, &driven);
    result.rows.push(Row {
        transport: GEN_ONLY.into(),
        points: args.points,
        rate_hz: args.rate_hz,
        frames: args.frames,
        cpu: Summary::of(&driven.cpu_ns),
        ..Default::default()
    });
    let mut expected_checksum = None;
    for &t in &args.transports {
        announce(args, t.name());
        let (driven, report) =
            measure_transport(rt, args, scope, dir, t, &mut result.notes).with_context(|| t.name().to_string())?;
        note_late(&mut result.notes, t.name(), &driven);
        if check_report(args, &report, &mut expected_checksum, &mut result.notes)? {
            result.verified.push(t.name().into());
        }
        let measured = report.latency_ns.len() as u64;
        if measured < args.frames {
            result.notes.push(format!(
                "{}: {} of {} measured clouds were not recorded (sequence gaps {}, bad stamps {})",
                t.name(),
                args.frames - measured,
                args.frames,
                report.seq_gaps,
                report.bad_stamps
            ));
        }
        result.rows.push(Row {
            transport: t.name().into(),
            points: args.points,
            rate_hz: args.rate_hz,
            frames: args.frames,
            lost: args.frames.saturating_sub(measured),
            cpu: Summary::of(&driven.cpu_ns),
            hop: Summary::of(&report.latency_ns),
            ready: Summary::of(&report.ready_ns),
            consumer_cpu: Summary::of(&report.cpu_ns),
        });
    }
    Ok(())
}

fn note_late(notes: &mut Vec<String>, name: &str, driven: &Driven) {
    if driven.late > 0 {
        notes.push(format!("{name}: {} clouds started more than one period late (schedule reset)", driven.late));
    }
}

/// The content must have arrived intact: no failed spot check, and when every cloud arrived, the
/// checksum over all of them equals the one computed here from the formula. Returns whether the
/// checksum was compared (false when clouds were missing).
fn check_report(
    args: &BenchArgs,
    report: &ConsumerReport,
    expected: &mut Option<u32>,
    notes: &mut Vec<String>,
) -> anyhow::Result<bool> {
    if report.bad_frames > 0 {
        bail!("{}: {} clouds arrived with wrong content or size", report.transport, report.bad_frames);
    }
    if report.received != args.total_frames() {
        notes.push(format!(
            "{}: {} of {} clouds received (warm-up included); checksum not compared",
            report.transport,
            report.received,
            args.total_frames()
        ));
        return Ok(false);
    }
    let want = *expected.get_or_insert_with(|| {
        let mut points = Vec::with_capacity(args.points);
        (0..args.total_frames()).fold(0u32, |acc, seq| {
            points.clear();
            points.extend((0..args.points).map(|i| bench_xyz(seq, i)));
            acc.wrapping_add(checksum_xyz(&points))
        })
    });
    ensure!(
        report.checksum == want,
        "{}: checksum of all received points {:#010x} != expected {want:#010x}",
        report.transport,
        report.checksum
    );
    Ok(true)
}

fn measure_transport(
    rt: &mut Runtime,
    args: &BenchArgs,
    scope: &IoxScope,
    dir: &Path,
    t: Transport,
    notes: &mut Vec<String>,
) -> anyhow::Result<(Driven, ConsumerReport)> {
    let report_timeout = Duration::from_secs_f64(args.total_frames() as f64 / args.rate_hz) + Duration::from_secs(60);
    match t {
        Transport::Iox => {
            let mut child = ConsumerProcess::spawn(t, args.points, args.warmup, scope, None)?;
            child.wait_line(READY_LINE, READY_TIMEOUT, &|| rt.termination_signal())?;
            let qos = service_spec(CLOUD).context("the cloud service is not in the contract")?.qos;
            let out = rt
                .output_slice_with_qos::<CloudPoint, CloudHeader>(CLOUD, &qos, args.points, IOX_DELIVERY)
                .context("creating the cloud publisher")?;
            let mut sink = IoxSink::new(out, args.points);
            let end = Instant::now() + READY_TIMEOUT;
            while sink.subscribers() == 0 {
                ensure!(Instant::now() < end, "the consumer's subscriber did not appear on {CLOUD}");
                std::thread::sleep(Duration::from_millis(10));
            }
            let driven = drive(rt, &mut sink, pacing(args))?;
            if sink.undelivered > 0 {
                notes.push(format!("iox: {} sends reached no subscriber", sink.undelivered));
            }
            let report = collect_report(&mut child, report_timeout, rt)?;
            Ok((driven, report))
        }
        Transport::SocketBincode | Transport::SocketRaw => {
            let path = dir.join(format!("{}.sock", t.name()));
            let listener = UnixListener::bind(&path).with_context(|| format!("cannot listen on {}", path.display()))?;
            let mut child = ConsumerProcess::spawn(t, args.points, args.warmup, scope, Some(&path))?;
            child.wait_line(READY_LINE, READY_TIMEOUT, &|| rt.termination_signal())?;
            let stream = accept_within(&listener, READY_TIMEOUT)?;
            let mut sink: Box<dyn FrameSink> = if t == Transport::SocketBincode {
                Box::new(SocketBincodeSink::new(stream, args.points))
            } else {
                Box::new(SocketRawSink::new(stream, args.points))
            };
            let driven = drive(rt, sink.as_mut(), pacing(args))?;
            let report = collect_report(&mut child, report_timeout, rt)?;
            Ok((driven, report))
        }
    }
}

/// Accepts a child's connection (it said READY after connecting, so this does not wait long).
pub(crate) fn accept_within(listener: &UnixListener, timeout: Duration) -> anyhow::Result<UnixStream> {
    listener.set_nonblocking(true).context("listener")?;
    let end = Instant::now() + timeout;
    loop {
        match listener.accept() {
            Ok((stream, _)) => {
                stream.set_nonblocking(false).context("socket")?;
                return Ok(stream);
            }
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock && Instant::now() < end => {
                std::thread::sleep(Duration::from_millis(5));
            }
            Err(e) => return Err(e).context("accepting a child process's connection"),
        }
    }
}

fn collect_report(child: &mut ConsumerProcess, timeout: Duration, rt: &Runtime) -> anyhow::Result<ConsumerReport> {
    let json = child.wait_line(REPORT_PREFIX, timeout, &|| rt.termination_signal())?;
    let report: ConsumerReport = serde_json::from_str(&json).context("malformed consumer report")?;
    let status = child.wait_exit(Duration::from_secs(10))?;
    ensure!(status.success(), "the consumer exited with {status}");
    Ok(report)
}

/// Runs the benchmark and prints the table to stdout (notes to stderr); writes the CSV if asked.
pub fn run_and_print(args: &BenchArgs) -> anyhow::Result<()> {
    let result = run_bench(args)?;
    let mib = (args.points * size_of::<CloudPoint>()) as f64 / (1024.0 * 1024.0);
    let cpus = std::thread::available_parallelism().map_or(0, |n| n.get());
    println!(
        "ingest_bench: {} points ({mib:.2} MiB) per cloud at {} Hz, {} measured clouds after {} warm-up per transport, \
         {cpus} CPUs; iceoryx2 prefix {} (removed)",
        args.points, args.rate_hz, args.frames, args.warmup, result.prefix
    );
    println!(
        "prod CPU = producer thread CPU per cloud (generate + send), -gen = minus the gen-only p50; \
         hop = publish -> consumer has read every point; ready = publish -> payload usable, before that read"
    );
    print!("{}", crate::report::render_table(&result.rows));
    if !result.verified.is_empty() {
        println!(
            "content verified (checksum over every point of all {} clouds): {}",
            args.total_frames(),
            result.verified.join(", ")
        );
    }
    for note in &result.notes {
        eprintln!("note: {note}");
    }
    if let Some(path) = &args.csv {
        crate::report::write_csv(path, &result.rows)?;
        eprintln!("ingest_bench: wrote {}", path.display());
    }
    Ok(())
}
