//! `pipeline-sensor-monitor`: subscribes every sensor service, validates each message (NaN/inf,
//! empty or oversized, stamps not increasing, unknown buoy ids), counts accepted and rejected
//! messages by reason, forwards end of stream, and writes the counters to `parts/<name>.json`.

use std::process::ExitCode;

use clap::Parser;
use pipeline_runtime::validate::{self, Guard};
use pipeline_runtime::{Flow, ProcessArgs, Runtime};
use shared_types::WireType;
use shared_types::services::{BUOY_RANGES, CLOUD, DEPTH, END_OF_STREAM, ODOMETRY, STEREO};
use shared_types::{
    BuoyRange, CloudHeader, CloudPoint, DepthReading, EndOfStream, MsgHeader, OdometryInput, StereoObservation,
    name_from32,
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

fn bytes_of<T: shared_types::WireType>(items: &[T]) -> impl Iterator<Item = &[u8]> {
    items.iter().map(|i| i.as_bytes())
}

struct Guards {
    digests: [Digest; 5],
    odometry: Guard,
    stereo: Guard,
    buoys: Guard,
    depth: Guard,
    cloud: Guard,
    cloud_points: u64,
    stereo_observations: u64,
    end_of_stream_seen: u64,
}

fn run(args: &ProcessArgs) -> anyhow::Result<pipeline_runtime::StopReason> {
    let (ctx, mut rt) = Runtime::start(args)?;
    let settings: SensorMonitorSettings = ctx.settings()?;
    let odometry = rt.input::<OdometryInput, MsgHeader>(ODOMETRY)?;
    let stereo = rt.input::<[StereoObservation], MsgHeader>(STEREO)?;
    let buoys = rt.input::<[BuoyRange], MsgHeader>(BUOY_RANGES)?;
    let depth = rt.input::<DepthReading, MsgHeader>(DEPTH)?;
    let cloud = rt.input::<[CloudPoint], CloudHeader>(CLOUD)?;
    let eos = rt.input::<EndOfStream, MsgHeader>(END_OF_STREAM)?;
    let mut g = Guards {
        digests: [Digest::default(); 5],
        odometry: Guard::new(ODOMETRY),
        stereo: Guard::new(STEREO),
        buoys: Guard::new(BUOY_RANGES),
        depth: Guard::new(DEPTH),
        cloud: Guard::new(CLOUD),
        cloud_points: 0,
        stereo_observations: 0,
        end_of_stream_seen: 0,
    };
    let known = settings.known_buoy_ids.clone();
    let result = rt.run(&mut g, None, |rt, g, _| {
        while let Some(s) = odometry.receive()? {
            g.odometry.note_seq(s.origin().value(), s.user_header().seq);
            let r = g
                .odometry
                .check_stamp(s.origin().value(), s.user_header().stamp_ns)
                .and_then(|_| validate::check_odometry(s.payload()));
            if g.odometry.admit(r) {
                g.digests[0].add(&s.user_header().stamp_ns.to_le_bytes());
                g.digests[0].add(s.payload().as_bytes());
            }
        }
        while let Some(s) = stereo.receive()? {
            g.stereo.note_seq(s.origin().value(), s.user_header().seq);
            let r = g
                .stereo
                .check_stamp(s.origin().value(), s.user_header().stamp_ns)
                .and_then(|_| validate::check_stereo(s.payload()));
            if g.stereo.admit(r) {
                g.stereo_observations += s.payload().len() as u64;
                g.digests[1].add(&s.user_header().stamp_ns.to_le_bytes());
                bytes_of(s.payload()).for_each(|b| g.digests[1].add(b));
            }
        }
        while let Some(s) = buoys.receive()? {
            g.buoys.note_seq(s.origin().value(), s.user_header().seq);
            let r = g
                .buoys
                .check_stamp(s.origin().value(), s.user_header().stamp_ns)
                .and_then(|_| validate::check_buoy_ranges(s.payload(), known.as_deref()));
            if g.buoys.admit(r) {
                g.digests[2].add(&s.user_header().stamp_ns.to_le_bytes());
                bytes_of(s.payload()).for_each(|b| g.digests[2].add(b));
            }
        }
        while let Some(s) = depth.receive()? {
            g.depth.note_seq(s.origin().value(), s.user_header().seq);
            let r = g
                .depth
                .check_stamp(s.origin().value(), s.user_header().stamp_ns)
                .and_then(|_| validate::check_depth(s.payload()));
            if g.depth.admit(r) {
                g.digests[3].add(&s.user_header().stamp_ns.to_le_bytes());
                g.digests[3].add(s.payload().as_bytes());
            }
        }
        while let Some(s) = cloud.receive()? {
            g.cloud.note_seq(s.origin().value(), s.user_header().msg.seq);
            let r = g
                .cloud
                .check_stamp(s.origin().value(), s.user_header().msg.stamp_ns)
                .and_then(|_| validate::check_cloud(s.user_header(), s.payload(), settings.max_cloud_points));
            if g.cloud.admit(r) {
                g.cloud_points += s.payload().len() as u64;
                let h = s.user_header();
                g.digests[4].add(&h.msg.stamp_ns.to_le_bytes());
                for v in h.sensor_origin_m.iter().chain(&h.orientation_xyzw) {
                    g.digests[4].add(&v.to_le_bytes());
                }
                bytes_of(s.payload()).for_each(|b| g.digests[4].add(b));
            }
        }
        while let Some(s) = eos.receive()? {
            let from = name_from32(&s.payload().process);
            if from != rt.name() {
                g.end_of_stream_seen += 1;
                tracing::info!(%from, "end of stream from upstream");
                if settings.forward_end_of_stream {
                    let total = g.odometry.accepted()
                        + g.stereo.accepted()
                        + g.buoys.accepted()
                        + g.depth.accepted()
                        + g.cloud.accepted();
                    rt.send_end_of_stream(total.saturating_sub(1), total)?;
                }
            }
        }
        Ok(Flow::Continue)
    });
    let part = serde_json::json!({ "sensor_monitor": {
        ODOMETRY: g.odometry.report(), STEREO: g.stereo.report(), BUOY_RANGES: g.buoys.report(),
        DEPTH: g.depth.report(), CLOUD: g.cloud.report(),
        "cloud_points": g.cloud_points, "stereo_observations": g.stereo_observations,
        "end_of_stream_seen": g.end_of_stream_seen,
        "digests": {
            ODOMETRY: format!("{:016x}", g.digests[0].0), STEREO: format!("{:016x}", g.digests[1].0),
            BUOY_RANGES: format!("{:016x}", g.digests[2].0), DEPTH: format!("{:016x}", g.digests[3].0),
            CLOUD: format!("{:016x}", g.digests[4].0),
        },
    }});
    let path = ctx.summary_part_path();
    std::fs::create_dir_all(path.parent().expect("parts dir"))?;
    std::fs::write(&path, serde_json::to_vec_pretty(&part)?)?;
    result
}

fn main() -> ExitCode {
    let args = ProcessArgs::parse();
    let _log = pipeline_runtime::logging::init(&args.name, args.log_format.unwrap_or_default());
    pipeline_runtime::exit_code(&run(&args))
}
