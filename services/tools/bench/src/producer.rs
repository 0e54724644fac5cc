//! The producer side: one [`FrameSink`] per transport (plus the no-transport [`GenOnlySink`]) and
//! [`drive`], which paces them at the configured rate inside [`Runtime::run`] (the WaitSet sleeps
//! until the next frame is due; nothing spins) and measures the thread CPU time of each frame.

use std::io::Write;
use std::os::unix::net::UnixStream;
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail, ensure};
use pipeline_runtime::{Flow, Output, Runtime, StopReason, monotonic_ns};
use shared_types::{CloudHeader, CloudPoint, FRAME_SENSOR, MsgHeader};

use crate::content::{
    BincodeCloudRef, RAW_END, RawHeader, SocketCloudHeader, bench_point, bench_xyz, bincode_config, xyz_as_bytes,
};
use crate::cpu::thread_cpu_ns;

/// Publishes one cloud per call; the CPU time of [`FrameSink::publish`] is "producer CPU per frame".
pub trait FrameSink {
    /// Produces cloud `seq` (generates every point) and sends it.
    fn publish(&mut self, seq: u64) -> anyhow::Result<()>;
    /// Tells the consumer that the stream has ended (after the last cloud).
    fn finish(&mut self, rt: &mut Runtime) -> anyhow::Result<()>;
}

/// Generates each baseline cloud into a reused `Vec<[f32; 3]>` (as a copy-based producer builds its
/// message), the same content the iceoryx2 sink writes in place.
fn generate(points: &mut Vec<[f32; 3]>, n: usize, seq: u64) {
    points.clear();
    points.extend((0..n).map(|i| bench_xyz(seq, i)));
}

/// Reference without any transport: only the content generation into a reused `Vec`.
pub struct GenOnlySink {
    points: Vec<[f32; 3]>,
    n: usize,
}

impl GenOnlySink {
    /// A sink for clouds of `n` points.
    pub fn new(n: usize) -> Self {
        Self { points: Vec::with_capacity(n), n }
    }
}

impl FrameSink for GenOnlySink {
    fn publish(&mut self, seq: u64) -> anyhow::Result<()> {
        generate(&mut self.points, self.n, seq);
        std::hint::black_box(&self.points);
        Ok(())
    }

    fn finish(&mut self, _rt: &mut Runtime) -> anyhow::Result<()> {
        Ok(())
    }
}

/// iceoryx2 through our runtime: loan a slice in shared memory, write every point in place with
/// `write_from_fn`, set the header, send (the runtime stamps `seq`/`publish_ns` and notifies).
pub struct IoxSink {
    out: Output<[CloudPoint], CloudHeader>,
    n: usize,
    /// Sends that reached no subscriber.
    pub undelivered: u64,
}

impl IoxSink {
    /// A sink publishing clouds of `n` points on `out`.
    pub fn new(out: Output<[CloudPoint], CloudHeader>, n: usize) -> Self {
        Self { out, n, undelivered: 0 }
    }

    /// Subscribers currently registered on the cloud service.
    pub fn subscribers(&self) -> usize {
        self.out.subscribers()
    }
}

impl FrameSink for IoxSink {
    fn publish(&mut self, seq: u64) -> anyhow::Result<()> {
        ensure!(self.out.next_seq() == seq, "runtime sequence {} != frame {seq}", self.out.next_seq());
        let sample = self.out.loan_slice_uninit(self.n)?;
        let mut sample = sample.write_from_fn(|i| bench_point(seq, i));
        *sample.user_header_mut() = CloudHeader {
            msg: MsgHeader { stamp_ns: monotonic_ns(), ..Default::default() },
            frame: FRAME_SENSOR,
            ..Default::default()
        };
        if self.out.send(sample)? == 0 {
            self.undelivered += 1;
        }
        Ok(())
    }

    fn finish(&mut self, rt: &mut Runtime) -> anyhow::Result<()> {
        let sent = self.out.sent();
        rt.send_end_of_stream(sent.saturating_sub(1), sent)?;
        Ok(())
    }
}

/// Copy baseline with bincode: the cloud as `Vec<[f32; 3]>` plus a [`SocketCloudHeader`], stamped
/// right before serialisation, encoded into a reused buffer behind an 8-byte length, written with
/// one `write_all` on a Unix stream socket.
pub struct SocketBincodeSink {
    stream: UnixStream,
    points: Vec<[f32; 3]>,
    buf: Vec<u8>,
    n: usize,
}

impl SocketBincodeSink {
    /// A sink writing clouds of `n` points to `stream`.
    pub fn new(stream: UnixStream, n: usize) -> Self {
        Self { stream, points: Vec::with_capacity(n), buf: Vec::new(), n }
    }
}

impl FrameSink for SocketBincodeSink {
    fn publish(&mut self, seq: u64) -> anyhow::Result<()> {
        let stamp_ns = monotonic_ns();
        generate(&mut self.points, self.n, seq);
        let header = SocketCloudHeader {
            stamp_ns,
            seq,
            origin_ns: stamp_ns,
            publish_ns: monotonic_ns(),
            frame: FRAME_SENSOR,
            ..Default::default()
        };
        self.buf.clear();
        self.buf.extend_from_slice(&[0; 8]);
        bincode::serde::encode_into_std_write(
            BincodeCloudRef { header, points: &self.points },
            &mut self.buf,
            bincode_config(),
        )
        .context("bincode encoding")?;
        let len = (self.buf.len() - 8) as u64;
        self.buf[..8].copy_from_slice(&len.to_le_bytes());
        self.stream.write_all(&self.buf).context("writing a bincode frame to the socket")
    }

    fn finish(&mut self, _rt: &mut Runtime) -> anyhow::Result<()> {
        self.stream.write_all(&0u64.to_le_bytes()).context("writing the end of stream to the socket")
    }
}

/// Copy baseline without serialisation: a [`RawHeader`] stamped right before the write, then the
/// points' bytes straight from the `Vec` (two `write_all` calls).
pub struct SocketRawSink {
    stream: UnixStream,
    points: Vec<[f32; 3]>,
    n: usize,
}

impl SocketRawSink {
    /// A sink writing clouds of `n` points to `stream`.
    pub fn new(stream: UnixStream, n: usize) -> Self {
        Self { stream, points: Vec::with_capacity(n), n }
    }
}

impl FrameSink for SocketRawSink {
    fn publish(&mut self, seq: u64) -> anyhow::Result<()> {
        let stamp_ns = monotonic_ns();
        generate(&mut self.points, self.n, seq);
        let header = RawHeader { points: self.n as u64, seq, stamp_ns, publish_ns: monotonic_ns() };
        self.stream.write_all(&header.to_bytes()).context("writing a raw frame header to the socket")?;
        self.stream.write_all(xyz_as_bytes(&self.points)).context("writing raw points to the socket")
    }

    fn finish(&mut self, _rt: &mut Runtime) -> anyhow::Result<()> {
        let end = RawHeader { points: RAW_END, seq: 0, stamp_ns: 0, publish_ns: 0 };
        self.stream.write_all(&end.to_bytes()).context("writing the end of stream to the socket")
    }
}

/// How many clouds to send and how fast.
#[derive(Debug, Clone, Copy)]
pub struct Pacing {
    /// Clouds sent first and not measured.
    pub warmup: u64,
    /// Measured clouds.
    pub frames: u64,
    /// Time between clouds.
    pub period: Duration,
}

/// What [`drive`] measured.
#[derive(Debug, Clone, Default)]
pub struct Driven {
    /// Producer thread CPU per measured cloud, ns.
    pub cpu_ns: Vec<u64>,
    /// Clouds that started more than one period after they were due (the schedule was reset).
    pub late: u64,
}

struct DriveState<'a> {
    sink: &'a mut dyn FrameSink,
    pacing: Pacing,
    next: u64,
    due: Instant,
    out: Driven,
}

/// Sends `warmup + frames` clouds through `sink`, one every `period` on an absolute schedule
/// (reset when a cloud starts more than a period late), then calls [`FrameSink::finish`]. The
/// runtime's WaitSet sleeps between clouds; SIGINT/SIGTERM abort with an error.
pub fn drive(rt: &mut Runtime, sink: &mut dyn FrameSink, pacing: Pacing) -> anyhow::Result<Driven> {
    let total = pacing.warmup + pacing.frames;
    let start = Instant::now();
    let mut st = DriveState { sink, pacing, next: 0, due: start, out: Driven::default() };
    rt.wake_at(start);
    let reason = rt.run(&mut st, None, |rt, st, wake| {
        if !wake.tick {
            return Ok::<_, anyhow::Error>(Flow::Continue);
        }
        let now = Instant::now();
        if now < st.due {
            rt.wake_at(st.due);
            return Ok(Flow::Continue);
        }
        let cpu0 = thread_cpu_ns();
        st.sink.publish(st.next)?;
        let cpu = thread_cpu_ns() - cpu0;
        if st.next >= st.pacing.warmup {
            st.out.cpu_ns.push(cpu);
        }
        st.next += 1;
        if st.next >= total {
            st.sink.finish(rt)?;
            return Ok(Flow::Stop);
        }
        let period = st.pacing.period;
        st.due = if now - st.due > period {
            st.out.late += 1;
            now + period
        } else {
            st.due + period
        };
        rt.wake_at(st.due);
        Ok(Flow::Continue)
    })?;
    if let StopReason::Signal(sig) = reason {
        bail!("interrupted by signal {sig}");
    }
    Ok(st.out)
}
