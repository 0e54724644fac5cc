//! `wire_roundtrip`: sends every wire type through iceoryx2 from one process to another and checks
//! the bytes. `--role sub` opens a subscriber per type, prints `READY`, and exits 0 once every type
//! arrived byte-identical (1 on a mismatch or timeout); `--role pub` sends one value of every type
//! (and a 1000-element cloud slice) filled with a per-type byte pattern, then lingers until stopped.

use std::fmt::Debug;
use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::{Duration, Instant};

use clap::Parser;
use iceoryx2::prelude::ZeroCopySend;
use pipeline_runtime::ports::{Input, Output};
use pipeline_runtime::{Flow, IoxScope, Runtime, RuntimeOptions};
use shared_types::services::Qos;
use shared_types::*;

#[derive(Debug, Parser)]
struct Args {
    /// `pub` or `sub`.
    #[arg(long)]
    role: String,
    /// iceoryx2 prefix.
    #[arg(long)]
    prefix: String,
    /// iceoryx2 root path.
    #[arg(long)]
    root: PathBuf,
    /// Give up after this long, s.
    #[arg(long, default_value_t = 20.0)]
    timeout_s: f64,
}

const QOS: Qos = Qos { history: 0, ..Qos::stream(2, 1) };
const SLICE_LEN: usize = 1000;

fn pattern(k: usize, len: usize) -> Vec<u8> {
    (0..len).map(|i| ((i * 131 + k * 17 + 7) % 251) as u8).collect()
}

fn value<T: WireType>(k: usize) -> T {
    T::from_bytes(&pattern(k, size_of::<T>())).expect("pattern has the type's size")
}

fn service<T: WireType>() -> String {
    format!("test/wire/{}", TypeLayout::of::<T>().rust_name)
}

trait Check {
    fn name(&self) -> String;
    /// Drains the input; Ok(true) once the expected value arrived.
    fn poll(&mut self) -> anyhow::Result<bool>;
}

struct Fixed<T: WireType + ZeroCopySend + Debug> {
    k: usize,
    input: Input<T, MsgHeader>,
    done: bool,
}

impl<T: WireType + ZeroCopySend + Debug> Check for Fixed<T> {
    fn name(&self) -> String {
        T::TYPE_NAME.to_string()
    }
    fn poll(&mut self) -> anyhow::Result<bool> {
        while let Some(s) = self.input.receive()? {
            anyhow::ensure!(
                s.payload().as_bytes() == pattern(self.k, size_of::<T>()),
                "{}: payload bytes differ",
                T::TYPE_NAME
            );
            anyhow::ensure!(s.user_header().stamp_ns == self.k as u64, "{}: header stamp differs", T::TYPE_NAME);
            self.done = true;
        }
        Ok(self.done)
    }
}

struct Cloud {
    input: Input<[CloudPoint], CloudHeader>,
    done: bool,
}

impl Check for Cloud {
    fn name(&self) -> String {
        format!("[{}] with {}", CloudPoint::TYPE_NAME, CloudHeader::TYPE_NAME)
    }
    fn poll(&mut self) -> anyhow::Result<bool> {
        while let Some(s) = self.input.receive()? {
            anyhow::ensure!(s.payload().len() == SLICE_LEN, "cloud slice has {} points", s.payload().len());
            for (i, p) in s.payload().iter().enumerate() {
                anyhow::ensure!(p.as_bytes() == value::<CloudPoint>(1000 + i).as_bytes(), "cloud point {i} differs");
            }
            let h = s.user_header();
            let mut expected: CloudHeader = value(999);
            expected.msg = *h.msg();
            anyhow::ensure!(h.as_bytes() == expected.as_bytes(), "cloud header differs");
            self.done = true;
        }
        Ok(self.done)
    }
}

macro_rules! for_each_wire_type {
    ($m:ident, $($arg:expr),*) => {
        $m!(MsgHeader, 0, $($arg),*);
        $m!(OdometryInput, 1, $($arg),*);
        $m!(StereoObservation, 2, $($arg),*);
        $m!(BuoyRange, 3, $($arg),*);
        $m!(DepthReading, 4, $($arg),*);
        $m!(CloudPoint, 5, $($arg),*);
        $m!(CloudHeader, 6, $($arg),*);
        $m!(PoseEstimate, 7, $($arg),*);
        $m!(Particle, 8, $($arg),*);
        $m!(ParticleSetHeader, 9, $($arg),*);
        $m!(Landmark, 10, $($arg),*);
        $m!(LandmarkMapHeader, 11, $($arg),*);
        $m!(BuoyFix, 12, $($arg),*);
        $m!(SlamDiagnostics, 21, $($arg),*);
        $m!(SyncedPair, 13, $($arg),*);
        $m!(FusedPose, 14, $($arg),*);
        $m!(MapStats, 15, $($arg),*);
        $m!(Voxel, 16, $($arg),*);
        $m!(VoxelSetHeader, 17, $($arg),*);
        $m!(Heartbeat, 18, $($arg),*);
        $m!(EndOfStream, 19, $($arg),*);
        $m!(ControlCommand, 20, $($arg),*);
        $m!(HeadingReading, 22, $($arg),*);
        $m!(LaserScanHeader, 23, $($arg),*);
        $m!(LaserRange, 24, $($arg),*);
        $m!(PlanarOdometry, 25, $($arg),*);
        $m!(PlanarPose, 26, $($arg),*);
        $m!(OccupancyGridHeader, 27, $($arg),*);
        $m!(OccupancyCell, 28, $($arg),*);
        $m!(TraversabilityCell, 29, $($arg),*);
    };
}

/// Number of fixed-size types above; a test checks it against `all_layouts()`.
const FIXED_TYPES: usize = 30;

fn subscribe(rt: &mut Runtime, timeout: Duration) -> anyhow::Result<()> {
    let mut checks: Vec<Box<dyn Check>> = vec![];
    macro_rules! sub {
        ($t:ty, $k:expr, $rt:expr, $checks:expr) => {
            let input = $rt.input_with_qos::<$t, MsgHeader>(&service::<$t>(), &QOS)?;
            $checks.push(Box::new(Fixed::<$t> { k: $k, input, done: false }));
        };
    }
    for_each_wire_type!(sub, rt, checks);
    anyhow::ensure!(checks.len() == FIXED_TYPES && FIXED_TYPES == all_layouts().len(), "type list out of date");
    let input = rt.input_with_qos::<[CloudPoint], CloudHeader>("test/wire/slice/CloudPoint", &QOS)?;
    checks.push(Box::new(Cloud { input, done: false }));
    println!("READY");
    std::io::stdout().flush()?;
    let deadline = Instant::now() + timeout;
    rt.run(&mut checks, Some(Duration::from_millis(100)), |_, checks, _| {
        let mut all = true;
        for c in checks.iter_mut() {
            all &= c.poll()?;
        }
        if all {
            return Ok(Flow::Stop);
        }
        if Instant::now() > deadline {
            let missing: Vec<_> =
                checks.iter_mut().filter_map(|c| (!c.poll().unwrap_or(false)).then(|| c.name())).collect();
            anyhow::bail!("timed out; never received: {missing:?}");
        }
        Ok(Flow::Continue)
    })?;
    for c in &checks {
        println!("OK {}", c.name());
    }
    Ok(())
}

fn publish(rt: &mut Runtime, linger: Duration) -> anyhow::Result<()> {
    macro_rules! publ {
        ($t:ty, $k:expr, $rt:expr, $keep:expr) => {
            let mut out: Output<$t, MsgHeader> =
                $rt.output_with_qos(&service::<$t>(), &QOS, pipeline_runtime::Delivery::DiscardWhenFull)?;
            out.send_value(MsgHeader { stamp_ns: $k, origin_ns: 1, ..Default::default() }, value::<$t>($k))?;
            $keep.push(Box::new(out)); // the publisher (and its samples) live until we return
        };
    }
    let mut keep: Vec<Box<dyn std::any::Any>> = vec![];
    for_each_wire_type!(publ, rt, keep);
    let mut cloud: Output<[CloudPoint], CloudHeader> = rt.output_slice_with_qos(
        "test/wire/slice/CloudPoint",
        &QOS,
        SLICE_LEN,
        pipeline_runtime::Delivery::DiscardWhenFull,
    )?;
    let mut s = cloud.loan_slice_uninit(SLICE_LEN)?.write_from_fn(|i| value::<CloudPoint>(1000 + i));
    *s.user_header_mut() = value::<CloudHeader>(999);
    s.user_header_mut().msg.origin_ns = 1;
    cloud.send(s)?;
    println!("SENT");
    std::io::stdout().flush()?;
    let end = Instant::now() + linger;
    rt.run(&mut (), Some(Duration::from_millis(100)), |_, _, _| {
        Ok::<_, anyhow::Error>(if Instant::now() > end { Flow::Stop } else { Flow::Continue })
    })?;
    Ok(())
}

fn main() -> ExitCode {
    let args = Args::parse();
    let _log = pipeline_runtime::logging::init(&format!("wire-{}", args.role), Default::default());
    let scope = IoxScope { prefix: args.prefix.clone(), root: args.root.clone(), base_config: None };
    let options = RuntimeOptions { publish_control: false, ..Default::default() };
    let timeout = Duration::from_secs_f64(args.timeout_s);
    let result = Runtime::new(&format!("wire-{}", args.role), &scope, options).map_err(anyhow::Error::from).and_then(
        |mut rt| match args.role.as_str() {
            "sub" => subscribe(&mut rt, timeout),
            "pub" => publish(&mut rt, timeout),
            other => anyhow::bail!("--role must be pub or sub, got `{other}`"),
        },
    );
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("wire_roundtrip: {e:#}");
            ExitCode::FAILURE
        }
    }
}
