//! The sensor monitor as a [`Stage`]: it subscribes every sensor service, validates each message
//! (NaN/inf, empty or oversized, stamps not increasing, unknown buoy ids), counts accepted and
//! rejected messages by reason with a digest of what it accepted, and ends after the first
//! upstream end of stream (the runtime's rule), sending its own when `forward_end_of_stream`.

use crate::checks as validate;
use pipeline_runtime::stage::{EndAfter, Ending, Stage, Step};
use pipeline_runtime::validate::{Guard, Rejection};
use pipeline_runtime::{Input, ProcessContext, Runtime, StageError, Wake};
use shared_types::WireType;
use shared_types::services::{BUOY_RANGES, CLOUD, DEPTH, HEADING, ODOMETRY, STEREO};
use shared_types::{
    BuoyRange, CloudHeader, CloudPoint, DepthReading, HeadingReading, MsgHeader, OdometryInput, StereoObservation,
};

use crate::SensorMonitorSettings;
use crate::summary::{SensorMonitorPart, SensorMonitorSummary};

/// FNV-1a over every accepted message's stamp and payload bytes, per service: two runs that
/// publish identical messages give identical digests.
#[derive(Debug, Default, Clone, Copy)]
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

/// The `sensor_monitor` stage.
pub struct SensorMonitorStage {
    settings: SensorMonitorSettings,
    inputs: Inputs,
    odometry: Stream,
    stereo: Stream,
    buoys: Stream,
    depth: Stream,
    heading: Stream,
    cloud: Stream,
    cloud_points: u64,
    stereo_observations: u64,
}

struct Inputs {
    odometry: Input<OdometryInput, MsgHeader>,
    stereo: Input<[StereoObservation], MsgHeader>,
    buoys: Input<[BuoyRange], MsgHeader>,
    depth: Input<DepthReading, MsgHeader>,
    heading: Input<HeadingReading, MsgHeader>,
    cloud: Input<[CloudPoint], CloudHeader>,
}

impl SensorMonitorStage {
    fn accepted(&self) -> u64 {
        [&self.odometry, &self.stereo, &self.buoys, &self.depth, &self.heading, &self.cloud]
            .iter()
            .map(|s| s.guard.accepted())
            .sum()
    }
}

impl Stage for SensorMonitorStage {
    type Settings = SensorMonitorSettings;

    fn open(_ctx: &ProcessContext, settings: SensorMonitorSettings, rt: &mut Runtime) -> Result<Self, StageError> {
        let inputs = Inputs {
            odometry: rt.input(ODOMETRY)?,
            stereo: rt.input(STEREO)?,
            buoys: rt.input(BUOY_RANGES)?,
            depth: rt.input(DEPTH)?,
            heading: rt.input(HEADING)?,
            cloud: rt.input(CLOUD)?,
        };
        Ok(Self {
            settings,
            inputs,
            odometry: Stream::new(ODOMETRY),
            stereo: Stream::new(STEREO),
            buoys: Stream::new(BUOY_RANGES),
            depth: Stream::new(DEPTH),
            heading: Stream::new(HEADING),
            cloud: Stream::new(CLOUD),
            cloud_points: 0,
            stereo_observations: 0,
        })
    }

    fn end_after(&self) -> EndAfter {
        EndAfter::FirstUpstream
    }

    fn step(&mut self, _rt: &mut Runtime, _wake: Wake, _inputs_ended: bool) -> Result<Step, StageError> {
        let i = &self.inputs;
        while let Some(s) = i.odometry.receive()? {
            let check = validate::check_odometry(s.payload());
            self.odometry.take(s.publisher_id(), s.user_header(), check, [s.payload().as_bytes()]);
        }
        while let Some(s) = i.stereo.receive()? {
            let check = validate::check_stereo(s.payload());
            let bytes = s.payload().iter().map(|o| o.as_bytes());
            if self.stereo.take(s.publisher_id(), s.user_header(), check, bytes) {
                self.stereo_observations += s.payload().len() as u64;
            }
        }
        while let Some(s) = i.buoys.receive()? {
            let check = validate::check_buoy_ranges(s.payload(), self.settings.known_buoy_ids.as_deref());
            self.buoys.take(s.publisher_id(), s.user_header(), check, s.payload().iter().map(|r| r.as_bytes()));
        }
        while let Some(s) = i.depth.receive()? {
            let check = validate::check_depth(s.payload());
            self.depth.take(s.publisher_id(), s.user_header(), check, [s.payload().as_bytes()]);
        }
        while let Some(s) = i.heading.receive()? {
            let check = validate::check_heading(s.payload());
            self.heading.take(s.publisher_id(), s.user_header(), check, [s.payload().as_bytes()]);
        }
        while let Some(s) = i.cloud.receive()? {
            let h = s.user_header();
            let check = validate::check_cloud(h, s.payload(), self.settings.max_cloud_points);
            let pose = [h.sensor_origin_m.as_slice(), h.orientation_xyzw.as_slice()].concat();
            let pose_bytes: Vec<u8> = pose.iter().flat_map(|v| v.to_le_bytes()).collect();
            let content = std::iter::once(pose_bytes.as_slice()).chain(s.payload().iter().map(|p| p.as_bytes()));
            if self.cloud.take(s.publisher_id(), &h.msg, check, content) {
                self.cloud_points += s.payload().len() as u64;
            }
        }
        Ok(Step::Idle)
    }

    type Summary = SensorMonitorPart;

    fn finish(&mut self, _rt: &mut Runtime, _ending: Ending) -> Result<Self::Summary, StageError> {
        let all = [
            (ODOMETRY, &self.odometry),
            (STEREO, &self.stereo),
            (BUOY_RANGES, &self.buoys),
            (DEPTH, &self.depth),
            (HEADING, &self.heading),
            (CLOUD, &self.cloud),
        ];
        Ok(SensorMonitorPart {
            sensor_monitor: SensorMonitorSummary {
                cloud_points: self.cloud_points,
                stereo_observations: self.stereo_observations,
                digests: all.iter().map(|(k, s)| (k.to_string(), format!("{:016x}", s.digest.0))).collect(),
                streams: all.iter().map(|(k, s)| (k.to_string(), s.guard.report())).collect(),
            },
        })
    }

    fn end_of_stream(&self) -> (u64, u64) {
        let total = self.accepted();
        (total.saturating_sub(1), total)
    }

    fn sends_end_of_stream(&self) -> bool {
        self.settings.forward_end_of_stream
    }
}
