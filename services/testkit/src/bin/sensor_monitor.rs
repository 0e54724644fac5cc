//! `sensor_monitor`: subscribes every sensor service, validates each message (NaN/inf,
//! empty or oversized, stamps not increasing, unknown buoy ids), counts accepted and rejected
//! messages by reason, forwards end of stream, and writes the counters to `parts/<name>.json`.

use std::process::ExitCode;

use pipeline_runtime::validate::{self, Guard, Rejection};
use pipeline_runtime::{Flow, ProcessArgs, Runtime};
use shared_types::WireType;
use shared_types::services::{BUOY_RANGES, CLOUD, DEPTH, END_OF_STREAM, HEADING, ODOMETRY, STEREO};
use shared_types::{
    BuoyRange, CloudHeader, CloudPoint, DepthReading, EndOfStream, HeadingReading, MsgHeader, OdometryInput,
    StereoObservation,
};
use testkit::SensorMonitorSettings;

/// FNV-1a over every accepted message's stamp and payload bytes, per service: two runs that
/// publish identical messages give identical digests.
#[derive(Default, Clone, Copy)]
struct Digest(u64);

impl Digest {
    fn add(&mut self, bytes: &[u8]) {
        let mut h = if self.0 == 0 { 0xcbf2_9ce4_8422_2325 } else { self.0 };
        for b in bytes {
            h ^= *b as u64;
            h = h.wrapping_mul(0x0000_0100_0000_01b3);
        }
        self.0 = h;
    }
}

/// One sensor stream: its guard and the digest of what it accepted.
struct Stream {
    guard: Guard,
    digest: Digest,
}

impl Stream {
    fn new(service: &str) -> Self {
        Self { guard: Guard::new(service), digest: Digest::default() }
    }

    /// Sequence, stamp and content checks of one message; when accepted, its stamp and `bytes`
    /// (its content, without the run-dependent publish/origin times) go into the digest.
    fn take<'a>(
        &mut self,
        origin: u128,
        header: &MsgHeader,
        content: Result<(), Rejection>,
        bytes: impl IntoIterator<Item = &'a [u8]>,
    ) -> bool {
        self.guard.note_seq(origin, header.seq);
        let verdict = self.guard.check_stamp(origin, header.stamp_ns).and(content);
        let accepted = self.guard.admit(verdict);
        if accepted {
            self.digest.add(&header.stamp_ns.to_le_bytes());
            bytes.into_iter().for_each(|b| self.digest.add(b));
        }
        accepted
    }
}

struct Monitor {
    odometry: Stream,
    stereo: Stream,
    buoys: Stream,
    depth: Stream,
    heading: Stream,
    cloud: Stream,
    cloud_points: u64,
    stereo_observations: u64,
    end_of_stream_seen: u64,
}

impl Monitor {
    fn accepted(&self) -> u64 {
        [&self.odometry, &self.stereo, &self.buoys, &self.depth, &self.heading, &self.cloud]
            .iter()
            .map(|s| s.guard.accepted())
            .sum()
    }
}

fn run(args: &ProcessArgs) -> anyhow::Result<pipeline_runtime::StopReason> {
    let (ctx, mut rt) = Runtime::start(args)?;
    let settings: SensorMonitorSettings = ctx.settings()?;
    let odometry = rt.input::<OdometryInput, MsgHeader>(ODOMETRY)?;
    let stereo = rt.input::<[StereoObservation], MsgHeader>(STEREO)?;
    let buoys = rt.input::<[BuoyRange], MsgHeader>(BUOY_RANGES)?;
    let depth = rt.input::<DepthReading, MsgHeader>(DEPTH)?;
    let heading = rt.input::<HeadingReading, MsgHeader>(HEADING)?;
    let cloud = rt.input::<[CloudPoint], CloudHeader>(CLOUD)?;
    let eos = rt.input::<EndOfStream, MsgHeader>(END_OF_STREAM)?;
    let mut g = Monitor {
        odometry: Stream::new(ODOMETRY),
        stereo: Stream::new(STEREO),
        buoys: Stream::new(BUOY_RANGES),
        depth: Stream::new(DEPTH),
        heading: Stream::new(HEADING),
        cloud: Stream::new(CLOUD),
        cloud_points: 0,
        stereo_observations: 0,
        end_of_stream_seen: 0,
    };
    let known = settings.known_buoy_ids.clone();
    let result = rt.run(&mut g, None, |rt, g, _| {
        let ended = rt.ended_upstream(&eos)?; // first: see Runtime::ended_upstream
        while let Some(s) = odometry.receive()? {
            let check = validate::check_odometry(s.payload());
            g.odometry.take(s.publisher_id(), s.user_header(), check, [s.payload().as_bytes()]);
        }
        while let Some(s) = stereo.receive()? {
            let check = validate::check_stereo(s.payload());
            if g.stereo.take(s.publisher_id(), s.user_header(), check, s.payload().iter().map(|o| o.as_bytes())) {
                g.stereo_observations += s.payload().len() as u64;
            }
        }
        while let Some(s) = buoys.receive()? {
            let check = validate::check_buoy_ranges(s.payload(), known.as_deref());
            g.buoys.take(s.publisher_id(), s.user_header(), check, s.payload().iter().map(|r| r.as_bytes()));
        }
        while let Some(s) = depth.receive()? {
            let check = validate::check_depth(s.payload());
            g.depth.take(s.publisher_id(), s.user_header(), check, [s.payload().as_bytes()]);
        }
        while let Some(s) = heading.receive()? {
            let check = validate::check_heading(s.payload());
            g.heading.take(s.publisher_id(), s.user_header(), check, [s.payload().as_bytes()]);
        }
        while let Some(s) = cloud.receive()? {
            let h = s.user_header();
            let check = validate::check_cloud(h, s.payload(), settings.max_cloud_points);
            let pose = [h.sensor_origin_m.as_slice(), h.orientation_xyzw.as_slice()].concat();
            let pose_bytes: Vec<u8> = pose.iter().flat_map(|v| v.to_le_bytes()).collect();
            let content = std::iter::once(pose_bytes.as_slice()).chain(s.payload().iter().map(|p| p.as_bytes()));
            if g.cloud.take(s.publisher_id(), &h.msg, check, content) {
                g.cloud_points += s.payload().len() as u64;
            }
        }
        for from in ended {
            g.end_of_stream_seen += 1;
            tracing::info!(%from, "end of stream from upstream");
            if settings.forward_end_of_stream && g.end_of_stream_seen == 1 {
                let total = g.accepted();
                rt.send_end_of_stream(total.saturating_sub(1), total)?;
            }
        }
        Ok(Flow::Continue)
    });
    let part = serde_json::json!({ "sensor_monitor": {
        ODOMETRY: g.odometry.guard.report(), STEREO: g.stereo.guard.report(), BUOY_RANGES: g.buoys.guard.report(),
        DEPTH: g.depth.guard.report(), HEADING: g.heading.guard.report(), CLOUD: g.cloud.guard.report(),
        "cloud_points": g.cloud_points, "stereo_observations": g.stereo_observations,
        "end_of_stream_seen": g.end_of_stream_seen,
        "digests": {
            ODOMETRY: format!("{:016x}", g.odometry.digest.0), STEREO: format!("{:016x}", g.stereo.digest.0),
            BUOY_RANGES: format!("{:016x}", g.buoys.digest.0), DEPTH: format!("{:016x}", g.depth.digest.0),
            HEADING: format!("{:016x}", g.heading.digest.0), CLOUD: format!("{:016x}", g.cloud.digest.0),
        },
    }});
    let path = ctx.summary_part_path();
    std::fs::create_dir_all(path.parent().expect("parts dir"))?;
    std::fs::write(&path, serde_json::to_vec_pretty(&part)?)?;
    result
}

fn main() -> ExitCode {
    pipeline_runtime::process_main::<testkit::SensorMonitorSettings, _>(run)
}
