//! Ingest as a [`Stage`]: the source's items published on the sensor services, paced on the
//! data clock (back-pressure when replaying as fast as possible), the ground truth written as it
//! becomes known, progress reported, and a restarted instance resuming where the killed one was.

use pipeline_runtime::StageError;
use std::path::Path;
use std::time::{Duration, Instant};

use crate::summary::{IngestPart, IngestSummary, MessageCounts};
use crate::{IngestSettings, Item, Pacer, Progress, SimSource, Source, SourceKind, TruthFile};
use pipeline_runtime::stage::{EndAfter, Ending, Stage, Step};
use pipeline_runtime::{Delivery, Output, ProcessContext, Restart, Runtime, Wake};
use shared_types::convert::quat_to_xyzw;
use shared_types::services::{self, BUOY_RANGES, CLOUD, DEPTH, HEADING, LASER, ODOMETRY, PLANAR_ODOMETRY, STEREO};
use shared_types::{
    BuoyRange, CLOUD_HAS_POSE, CloudHeader, CloudPoint, DepthReading, FRAME_SENSOR, HeadingReading, LaserRange,
    LaserScanHeader, MsgHeader, OdometryInput, PlanarOdometry, StereoObservation,
};

struct Outputs {
    odometry: Output<OdometryInput, MsgHeader>,
    stereo: Output<[StereoObservation], MsgHeader>,
    buoys: Output<[BuoyRange], MsgHeader>,
    depth: Output<DepthReading, MsgHeader>,
    heading: Output<HeadingReading, MsgHeader>,
    cloud: Output<[CloudPoint], CloudHeader>,
    laser: Output<[LaserRange], LaserScanHeader>,
    planar_odometry: Output<PlanarOdometry, MsgHeader>,
}

/// The `ingest` stage: a source (it ends itself at the end of its data).
pub struct IngestStage {
    source: Box<dyn Source>,
    /// `ground_truth.tum`, written as the source learns it (before the items it belongs to go out).
    truth: TruthFile,
    outputs: Outputs,
    pacer: Pacer,
    pending: Option<Item>,
    /// Clouds a little after the rest (factor 0, `cloud_lag_s`).
    reorder: crate::reorder::CloudLag,
    out_dir: std::path::PathBuf,
    progress_every: Option<Duration>,
    last_progress: Instant,
    started: Instant,
    counts: [u64; 8],
    empty_clouds: u64,
    first_last_stamp: Option<(u64, u64)>,
    publish_from: Instant,
    /// Items taken from the source so far (this instance and the killed ones before it).
    items: u64,
    /// Items still to take without publishing: what a killed instance had published already.
    skip: u64,
    /// With factor 0: how long to wait for a lost subscriber to come back.
    resubscribe_wait: Option<Duration>,
    /// Most subscribers seen per output (odometry, stereo, buoy ranges, depth, cloud, heading,
    /// laser, planar odometry).
    subscribers: [usize; 8],
    /// Since when publishing waits for a lost subscriber.
    waiting: Option<Instant>,
}

/// The output (index into `counts`) an item goes to.
fn output_index(item: &Item) -> usize {
    match item {
        Item::Odometry { .. } => 0,
        Item::Stereo { .. } => 1,
        Item::BuoyRanges { .. } => 2,
        Item::Depth { .. } => 3,
        Item::Cloud { .. } => 4,
        Item::Heading { .. } => 5,
        Item::Laser { .. } => 6,
        Item::PlanarOdometry { .. } => 7,
    }
}

fn header(stamp_ns: u64) -> MsgHeader {
    MsgHeader { stamp_ns, ..Default::default() }
}

impl IngestStage {
    fn publish(&mut self, rt: &mut Runtime, item: Item) -> Result<(), StageError> {
        let stamp = item.stamp_ns();
        self.first_last_stamp = Some(self.first_last_stamp.map_or((stamp, stamp), |(a, _)| (a, stamp)));
        self.items += 1;
        // Recorded before the send: a kill in between loses this item, never duplicates it.
        let (counts, empty_clouds) = (self.counts, self.empty_clouds);
        let mut p = Progress { items: self.items, counts, empty_clouds, first_last_stamp: self.first_last_stamp };
        match &item {
            Item::Odometry { .. } => p.counts[0] += 1,
            Item::Stereo { .. } => p.counts[1] += 1,
            Item::BuoyRanges { .. } => p.counts[2] += 1,
            Item::Depth { .. } => p.counts[3] += 1,
            Item::Cloud { points, .. } if points.is_empty() => p.empty_clouds += 1,
            Item::Cloud { .. } => p.counts[4] += 1,
            Item::Heading { .. } => p.counts[5] += 1,
            Item::Laser { .. } => p.counts[6] += 1,
            Item::PlanarOdometry { .. } => p.counts[7] += 1,
        }
        rt.state().record(&p.encode());
        rt.state().flush()?;
        let o = &mut self.outputs;
        match item {
            Item::Odometry { stamp_ns, input } => {
                o.odometry.send_value(header(stamp_ns), input)?;
                self.counts[0] += 1;
            }
            Item::Stereo { stamp_ns, observations } => {
                let mut s = o.stereo.loan_slice_uninit(observations.len())?.write_from_slice(&observations);
                *s.user_header_mut() = header(stamp_ns);
                o.stereo.send(s)?;
                self.counts[1] += 1;
            }
            Item::BuoyRanges { stamp_ns, ranges } => {
                let mut s = o.buoys.loan_slice_uninit(ranges.len())?.write_from_slice(&ranges);
                *s.user_header_mut() = header(stamp_ns);
                o.buoys.send(s)?;
                self.counts[2] += 1;
            }
            Item::Depth { stamp_ns, reading } => {
                o.depth.send_value(header(stamp_ns), reading)?;
                self.counts[3] += 1;
            }
            Item::Heading { stamp_ns, reading } => {
                o.heading.send_value(header(stamp_ns), reading)?;
                self.counts[5] += 1;
            }
            Item::Laser { stamp_ns, header: h, ranges } => {
                let mut s =
                    o.laser.loan_slice_uninit(ranges.len())?.write_from_fn(|i| LaserRange { range_m: ranges[i] });
                *s.user_header_mut() = LaserScanHeader { msg: header(stamp_ns), beams: ranges.len() as u32, ..h };
                o.laser.send(s)?;
                self.counts[6] += 1;
            }
            Item::PlanarOdometry { stamp_ns, odometry } => {
                o.planar_odometry.send_value(header(stamp_ns), odometry)?;
                self.counts[7] += 1;
            }
            Item::Cloud { stamp_ns, world_from_sensor, points } => {
                if points.is_empty() {
                    self.empty_clouds += 1;
                    return Ok(());
                }
                let mut s = o.cloud.loan_slice_uninit(points.len())?.write_from_fn(|i| CloudPoint {
                    x_m: points[i][0],
                    y_m: points[i][1],
                    z_m: points[i][2],
                });
                let h = s.user_header_mut();
                *h = CloudHeader { msg: header(stamp_ns), frame: FRAME_SENSOR, ..Default::default() };
                if let Some(pose) = world_from_sensor {
                    h.sensor_origin_m = pose.translation.vector.into();
                    h.orientation_xyzw = quat_to_xyzw(&pose.rotation);
                    h.flags = CLOUD_HAS_POSE;
                }
                o.cloud.send(s)?;
                self.counts[4] += 1;
            }
        }
        Ok(())
    }

    /// The next item of the source, its ground truth written first.
    fn next_item(&mut self) -> Result<Option<Item>, StageError> {
        let (source, truth) = (&mut self.source, &mut self.truth);
        self.reorder.next(|| {
            let item = source.next_item()?;
            truth.update(&**source)?;
            Ok::<_, StageError>(item)
        })
    }

    /// This process's part of summary.json: at the end of the source, or what was published
    /// so far when the run is stopped first (`completed: false`).
    fn part(&self, rt: &Runtime, completed: bool) -> IngestPart {
        let c = &self.counts;
        IngestPart {
            ingest: IngestSummary {
                source: self.source.describe(),
                completed,
                progress: self.source.progress(),
                messages: MessageCounts {
                    odometry: c[0],
                    stereo: c[1],
                    buoy_ranges: c[2],
                    depth: c[3],
                    cloud: c[4],
                    heading: c[5],
                    laser: c[6],
                    planar_odometry: c[7],
                },
                empty_clouds_skipped: self.empty_clouds,
                data_warts: self.source.warts().into_iter().map(|(k, n)| (k.to_string(), n)).collect(),
                ground_truth_samples: self.truth.written() as u64,
                data_duration_s: self.first_last_stamp.map_or(0.0, |(a, b)| (b - a) as f64 / 1e9),
                wall_duration_s: self.started.elapsed().as_secs_f64(),
                backpressure_wait_s: rt.backpressure_waited().as_secs_f64(),
                details: self.source.details(),
            },
        }
    }

    fn subscribers(&self, k: usize) -> usize {
        let o = &self.outputs;
        match k {
            0 => o.odometry.subscribers(),
            1 => o.stereo.subscribers(),
            2 => o.buoys.subscribers(),
            3 => o.depth.subscribers(),
            4 => o.cloud.subscribers(),
            5 => o.heading.subscribers(),
            6 => o.laser.subscribers(),
            _ => o.planar_odometry.subscribers(),
        }
    }

    /// With factor 0: true while output `k`'s service has fewer subscribers than it had (a consumer
    /// died and is being restarted) and `resubscribe_wait_s` has not passed since that was seen.
    fn wait_for_lost_subscriber(&mut self, k: usize, now: Instant) -> bool {
        let Some(wait) = self.resubscribe_wait else { return false };
        let n = self.subscribers(k);
        if n >= self.subscribers[k] {
            self.subscribers[k] = n;
            if let Some(since) = self.waiting.take() {
                tracing::info!(
                    "the lost subscriber is back after {:.1} s: publishing again",
                    (now - since).as_secs_f64()
                );
            }
            return false;
        }
        let service = match k {
            0 => ODOMETRY,
            1 => STEREO,
            2 => BUOY_RANGES,
            3 => DEPTH,
            4 => CLOUD,
            5 => HEADING,
            6 => LASER,
            _ => PLANAR_ODOMETRY,
        };
        let since = *self.waiting.get_or_insert_with(|| {
            tracing::info!(
                service,
                "{} of {} subscribers left: waiting up to {:.1} s for a restarted consumer before publishing on",
                n,
                self.subscribers[k],
                wait.as_secs_f64()
            );
            now
        });
        if now - since < wait {
            return true;
        }
        tracing::warn!(
            service,
            "the lost subscriber did not come back within {:.1} s: going on without it",
            wait.as_secs_f64()
        );
        self.subscribers[k] = n;
        self.waiting = None;
        false
    }

    fn nudge_all(&self) -> Result<(), StageError> {
        let o = &self.outputs;
        o.odometry.nudge()?;
        o.stereo.nudge()?;
        o.buoys.nudge()?;
        o.depth.nudge()?;
        o.heading.nudge()?;
        o.cloud.nudge()?;
        o.laser.nudge()?;
        o.planar_odometry.nudge()?;
        Ok(())
    }

    /// Publishes every item that is due; asks to be woken for the next one.
    fn pump(&mut self, rt: &mut Runtime) -> Result<Step, StageError> {
        if self.skip > 0 {
            // A restart: take what the killed instance had published from the (deterministic)
            // source without publishing it, in batches so that heartbeats go on meanwhile.
            let batch_end = Instant::now() + Duration::from_millis(50);
            while self.skip > 0 && Instant::now() < batch_end {
                if self.next_item()?.is_none() {
                    return Err(StageError::msg(format!(
                        "the source ended {} items before the point the killed instance had reached: \
                         it is not the same source (config changed?)",
                        self.skip
                    )));
                }
                self.skip -= 1;
            }
            if self.skip == 0 {
                tracing::info!(
                    items = self.items,
                    "resumed after the {} items the killed instance had published, in {:.1} s",
                    self.items,
                    self.started.elapsed().as_secs_f64()
                );
            }
            self.nudge_all()?;
            rt.wake_at(Instant::now());
            return Ok(Step::Idle);
        }
        if Instant::now() < self.publish_from {
            // Wake every subscriber so that it attaches to our publishers before the first message.
            self.nudge_all()?;
            rt.wake_at(self.publish_from.min(Instant::now() + Duration::from_millis(25)));
            return Ok(Step::Idle);
        }
        let batch_end = Instant::now() + Duration::from_millis(20);
        if let Some(p) = self.source.progress() {
            rt.set_progress(p);
        }
        loop {
            let now = Instant::now();
            if let Some(every) = self.progress_every
                && now - self.last_progress >= every
            {
                self.last_progress = now;
                let pct = self.source.progress().map(|p| format!("{:.0}%", p * 100.0)).unwrap_or_else(|| "?".into());
                tracing::info!("progress {pct}: {} messages", self.counts.iter().sum::<u64>());
            }
            if self.pending.is_none() {
                match self.next_item()? {
                    Some(item) => self.pending = Some(item),
                    None => return Ok(Step::Done),
                }
            }
            let stamp = self.pending.as_ref().expect("filled above").stamp_ns();
            if let Some(due) = self.pacer.due(stamp, now)
                && due > now
            {
                rt.wake_at(due);
                break;
            }
            if self.wait_for_lost_subscriber(output_index(self.pending.as_ref().expect("filled above")), now) {
                rt.wake_at(now + Duration::from_millis(20));
                break;
            }
            let item = self.pending.take().expect("filled above");
            self.publish(rt, item)?;
            if Instant::now() >= batch_end {
                rt.wake_at(Instant::now()); // let the loop publish heartbeats, then go on
                break;
            }
        }
        Ok(Step::Idle)
    }
}

fn make_source(settings: &IngestSettings, _config_dir: &Path, out_dir: &Path) -> Result<Box<dyn Source>, StageError> {
    Ok(match settings.source {
        SourceKind::Sim => Box::new(SimSource::new(settings.sim.clone(), out_dir)?),
        SourceKind::StereoSim => Box::new(crate::StereoSimSource::new(&settings.stereo_sim, out_dir)?),
        SourceKind::Indoor => Box::new(crate::indoor::IndoorSource::new(settings.indoor.clone(), out_dir)?),
        other => file_source(other, settings, _config_dir, out_dir)?,
    })
}

impl Stage for IngestStage {
    type Settings = IngestSettings;

    fn open(ctx: &ProcessContext, settings: IngestSettings, rt: &mut Runtime) -> Result<Self, StageError> {
        let config_dir = ctx.config.source.parent().unwrap_or(Path::new(".")).to_path_buf();
        let source = make_source(&settings, &config_dir, &ctx.out_dir)?;
        tracing::info!(real_time_factor = settings.real_time_factor, "source: {}", source.describe());
        let delivery = if settings.real_time_factor > 0.0 {
            Delivery::DiscardWhenFull
        } else {
            Delivery::WaitWhenFull {
                max_wait: (settings.backpressure_max_wait_s > 0.0)
                    .then(|| Duration::from_secs_f64(settings.backpressure_max_wait_s)),
            }
        };
        let qos = |s: &str| services::service_spec(s).expect("sensor services are in the contract").qos;
        let cloud_len = crate::initial_cloud_len(&settings);
        let outputs = Outputs {
            odometry: rt.output_with_qos(ODOMETRY, &qos(ODOMETRY), delivery)?,
            stereo: rt.output_slice_with_qos(STEREO, &qos(STEREO), 1024, delivery)?,
            buoys: rt.output_slice_with_qos(BUOY_RANGES, &qos(BUOY_RANGES), 16, delivery)?,
            depth: rt.output_with_qos(DEPTH, &qos(DEPTH), delivery)?,
            heading: rt.output_with_qos(HEADING, &qos(HEADING), delivery)?,
            cloud: rt.output_slice_with_qos(CLOUD, &qos(CLOUD), cloud_len, delivery)?,
            laser: rt.output_slice_with_qos(LASER, &qos(LASER), crate::initial_laser_len(&settings), delivery)?,
            planar_odometry: rt.output_with_qos(PLANAR_ODOMETRY, &qos(PLANAR_ODOMETRY), delivery)?,
        };
        let start = Progress::default();
        let mut truth = TruthFile::create(&ctx.out_dir)?;
        truth.update(&*source)?;
        let state = IngestStage {
            source,
            truth,
            outputs,
            pacer: Pacer::new(settings.real_time_factor),
            reorder: crate::reorder::CloudLag::new(if settings.real_time_factor == 0.0 {
                (settings.cloud_lag_s * 1e9) as u64
            } else {
                0
            }),
            pending: None,
            out_dir: ctx.out_dir.clone(),
            progress_every: (settings.progress_interval_s > 0.0)
                .then(|| Duration::from_secs_f64(settings.progress_interval_s)),
            last_progress: Instant::now(),
            started: Instant::now(),
            counts: start.counts,
            empty_clouds: start.empty_clouds,
            first_last_stamp: start.first_last_stamp,
            publish_from: Instant::now() + Duration::from_secs_f64(settings.connect_grace_s),
            items: start.items,
            skip: start.items,
            resubscribe_wait: (settings.real_time_factor <= 0.0 && settings.resubscribe_wait_s > 0.0)
                .then(|| Duration::from_secs_f64(settings.resubscribe_wait_s)),
            subscribers: [0; 8],
            waiting: None,
        };
        rt.wake_at(Instant::now());
        Ok(state)
    }

    /// A restarted instance resumes after what the killed one had published (its last progress
    /// record): the items it took are taken again from the (deterministic) source, unpublished.
    fn restore(&mut self, restart: Restart) -> Result<usize, StageError> {
        let (progress, lines) = crate::progress::restored(&restart.journal);
        if let Some(p) = progress {
            tracing::info!(items = p.items, "restarted: skipping the items the killed instance had published");
            self.counts = p.counts;
            self.empty_clouds = p.empty_clouds;
            self.first_last_stamp = p.first_last_stamp;
            self.items = p.items;
            self.skip = p.items;
        }
        Ok(lines)
    }

    fn end_after(&self) -> EndAfter {
        EndAfter::Itself
    }

    fn tick(&self) -> Option<Duration> {
        Some(Duration::from_millis(500))
    }

    fn step(&mut self, rt: &mut Runtime, _wake: Wake, _inputs_ended: bool) -> Result<Step, StageError> {
        self.pump(rt)
    }

    type Summary = IngestPart;

    fn finish(&mut self, rt: &mut Runtime, ending: Ending) -> Result<Self::Summary, StageError> {
        let sent: u64 = self.counts.iter().sum();
        let completed = ending == Ending::EndOfStream;
        if completed {
            self.source.finish(&self.out_dir)?;
            self.truth.update(&*self.source)?;
            let data_s = self.first_last_stamp.map_or(0.0, |(a, b)| (b - a) as f64 / 1e9);
            let wall_s = self.started.elapsed().as_secs_f64();
            tracing::info!("source exhausted: {sent} messages, {data_s:.1} s of data in {wall_s:.1} s");
        } else {
            // The ground truth so far is on disk already.
            tracing::info!(
                ground_truth_samples = self.truth.written(),
                "stopped before the end of the source: {sent} messages published"
            );
        }
        Ok(self.part(rt, completed))
    }

    fn end_of_stream(&self) -> (u64, u64) {
        let sent: u64 = self.counts.iter().sum();
        (sent.saturating_sub(1), sent)
    }
}

/// Creates the replay source for `kind` (everything but the simulator).
fn file_source(
    kind: crate::SourceKind,
    settings: &crate::IngestSettings,
    config_dir: &std::path::Path,
    _out_dir: &std::path::Path,
) -> Result<Box<dyn crate::Source>, crate::SourceError> {
    use crate::SourceKind::*;
    Ok(match kind {
        Sim | StereoSim | Indoor => {
            return Err(crate::SourceError::Settings("a simulator is not a file source".into()));
        }
        Plaza2 => {
            Box::new(crate::Plaza2Source::load(&crate::resolve(config_dir, &settings.plaza2.dir), &settings.plaza2)?)
        }
        StereoVo => Box::new(crate::StereoVoSource::load(
            &crate::resolve(config_dir, &settings.stereo_vo.dir),
            &settings.stereo_vo,
        )?),
        Clouds => Box::new(crate::CloudFileSource::new(config_dir, &settings.clouds)?),
        Carmen => Box::new(crate::carmen::CarmenSource::load(config_dir, &settings.carmen)?),
        DepthImages => Box::new(crate::DepthImageSource::new(config_dir, &settings.depth_images)?),
        Rosbag2 => Box::new(crate::rosbag2::Rosbag2Source::open(config_dir, &settings.rosbag2)?),
    })
}
