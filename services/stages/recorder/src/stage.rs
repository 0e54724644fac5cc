//! The recorder as a [`Stage`]: its taps (one subscriber per recorded service) drained into the
//! MCAP sink on every wake-up. It ends after every process in `end_after` has ended (the runtime's
//! rule; with an empty list it records until it is stopped) and always leaves a complete file:
//! [`Stage::finish`] drains what is queued and writes the file's summary, whether the inputs
//! ended or a signal stopped it. A restarted recorder keeps the file of the killed instance
//! (renamed `<stem>.part<N>.<ext>`, cut short at its last complete chunk: `mcap recover` reads it)
//! and records the rest of the run in a new file under the configured name.

use pipeline_runtime::StageError;
use std::collections::{BTreeMap, HashMap};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use pipeline_runtime::stage::{EndAfter, Ending, Stage, Step};
use pipeline_runtime::{ProcessContext, Restart, Runtime, Wake, monotonic_ns};

use crate::summary::{RecorderPart, RecordingSummary, Ros2BagSummary};
use crate::{McapSink, RecorderSettings, SinkOptions, Tap, Topic};

/// Per-topic counters.
#[derive(Debug, Default, Clone, Copy)]
struct Counts {
    received: u64,
    missed: u64,
}

/// The `recorder` stage.
pub struct RecorderStage {
    settings: RecorderSettings,
    path: PathBuf,
    /// The MCAP writer, created at the first wake-up (after a restart has moved the killed
    /// instance's file aside); `None` before and after.
    sink: Option<McapSink>,
    /// What the file is created with, until it is.
    to_create: Option<(SinkOptions, BTreeMap<String, String>)>,
    /// Files of killed instances, kept under another name.
    earlier_parts: Vec<String>,
    /// The services recorded into the MCAP file (its channel order).
    topics: Vec<&'static Topic>,
    /// One per service read: the recorded ones, then those only the ROS 2 bag reads.
    taps: Vec<Box<dyn Tap>>,
    /// Per tap: its channel in the MCAP file (`None`: read for the ROS 2 bag only).
    channel: Vec<Option<usize>>,
    /// Per tap: the ROS 2 bag reads it.
    to_ros2: Vec<bool>,
    /// The ROS 2 bag (`ros2`), created with the file; its directory until then.
    ros2: Option<crate::Ros2Sink>,
    ros2_dir: Option<PathBuf>,
    /// Directories of killed instances' ROS 2 bags, kept under another name.
    earlier_ros2_parts: Vec<String>,
    skipped: BTreeMap<String, String>,
    counts: Vec<Counts>,
    /// Last sequence number per (topic, publisher): a gap is counted as missed.
    last_seq: HashMap<(usize, u128), u64>,
    first_receive: Option<Instant>,
    last_receive: Option<Instant>,
    started: Instant,
    /// Messages written, for the end of stream.
    written: u64,
}

impl RecorderStage {
    /// Creates the file (once).
    fn create(&mut self) -> Result<(), StageError> {
        if let Some((options, metadata)) = self.to_create.take() {
            if let (Some(dir), Some(r)) = (&self.ros2_dir, &self.settings.ros2) {
                // A restarted instance moved the killed one's bag aside in `restore`.
                if !pipeline_runtime::restart::is_restart()
                    && let ros2_interop::NewBag::ReplacedEarlierRun { removed } =
                        ros2_interop::prepare_bag_dir(dir, false).map_err(|e| crate::RecorderError::Message {
                            service: dir.display().to_string(),
                            what: e.to_string(),
                        })?
                {
                    tracing::info!(dir = %dir.display(), "replacing an earlier run's ROS 2 bag ({} directory(ies) removed)", removed.len());
                }
                let sink = crate::Ros2Sink::create(dir, r, self.settings.queue_messages)?;
                tracing::info!(dir = %dir.display(), topics = r.out.len(), "recording a ROS 2 bag");
                self.ros2 = Some(sink);
            }
            self.sink = Some(McapSink::create(&self.path, &self.topics, &options, metadata)?);
            tracing::info!(
                file = %self.path.display(),
                topics = self.topics.len(),
                not_recorded = self.skipped.len(),
                "recording"
            );
        }
        Ok(())
    }

    /// Drains every tap into the sink; returns how many messages there were.
    fn drain(&mut self) -> Result<usize, StageError> {
        let mut total = 0;
        let Self { sink, taps, counts, last_seq, channel, to_ros2, ros2, .. } = self;
        let Some(sink) = sink.as_ref() else { return Ok(0) };
        let mut failed = None;
        for (index, tap) in taps.iter().enumerate() {
            let (channel, to_ros2) = (channel[index], to_ros2[index]);
            let service = tap.service();
            total += tap
                .drain(&mut |r| {
                    let c = &mut counts[index];
                    c.received += 1;
                    if let Some(last) = last_seq.insert((index, r.publisher), r.msg.seq)
                        && r.msg.seq > last + 1
                    {
                        c.missed += r.msg.seq - last - 1;
                    }
                    let mut data = Vec::with_capacity(r.header.len() + r.payload.len());
                    data.extend_from_slice(r.header);
                    data.extend_from_slice(r.payload);
                    let mut result = Ok(());
                    if to_ros2 && let Some(ros2) = ros2.as_ref() {
                        let copy = if channel.is_some() { data.clone() } else { std::mem::take(&mut data) };
                        result = ros2.write(service, crate::ros2::unix_ns(), copy);
                    }
                    if let (Ok(()), Some(channel)) = (&result, channel) {
                        result = sink.write(channel, monotonic_ns(), r.msg.publish_ns, data);
                    }
                    match result {
                        Ok(()) => std::ops::ControlFlow::Continue(()),
                        Err(e) => {
                            failed = Some(e);
                            std::ops::ControlFlow::Break(())
                        }
                    }
                })
                .map_err(crate::RecorderError::from)?;
            if let Some(e) = failed.take() {
                return Err(e.into());
            }
        }
        if total > 0 {
            let now = Instant::now();
            self.first_receive.get_or_insert(now);
            self.last_receive = Some(now);
        }
        Ok(total)
    }
}

impl Stage for RecorderStage {
    type Settings = RecorderSettings;

    fn open(ctx: &ProcessContext, settings: RecorderSettings, rt: &mut Runtime) -> Result<Self, StageError> {
        let mut topics: Vec<&'static Topic> = vec![];
        let mut taps = vec![];
        let (mut channel, mut to_ros2) = (vec![], vec![]);
        let mut skipped = BTreeMap::new();
        let ros2_services = settings.ros2.as_ref().map(|r| r.services()).unwrap_or_default();
        for t in settings.topics() {
            match t.tap(rt) {
                Ok(tap) => {
                    taps.push(tap);
                    channel.push(Some(topics.len()));
                    to_ros2.push(ros2_services.contains(&t.service));
                    topics.push(t);
                }
                Err(e) => {
                    tracing::warn!(service = t.service, "not recorded: {e}");
                    skipped.insert(t.service.to_string(), e.to_string());
                }
            }
        }
        // What the ROS 2 bag is made from and the MCAP file leaves out.
        for service in &ros2_services {
            if topics.iter().any(|t| t.service == *service) {
                continue;
            }
            let t = crate::topic(service).ok_or_else(|| {
                StageError::stage(crate::RecorderError::Message {
                    service: service.to_string(),
                    what: "not a recordable service".into(),
                })
            })?;
            taps.push(t.tap(rt)?);
            channel.push(None);
            to_ros2.push(true);
        }
        let path = settings.path(&ctx.out_dir);
        let config_text = std::fs::read_to_string(&ctx.config.source).unwrap_or_default();
        let metadata = BTreeMap::from([
            ("pipeline_version".to_string(), env!("CARGO_PKG_VERSION").to_string()),
            ("wire_version".to_string(), shared_types::WIRE_VERSION.to_string()),
            ("recorder".to_string(), ctx.name.clone()),
            ("config_file".to_string(), ctx.config.source.display().to_string()),
            ("config".to_string(), config_text),
            ("iceoryx_prefix".to_string(), ctx.scope.prefix.clone()),
            ("log_time".to_string(), "CLOCK_MONOTONIC ns at receive".to_string()),
            ("publish_time".to_string(), "the message's publish_ns (CLOCK_MONOTONIC ns at send)".to_string()),
            ("not_recorded".to_string(), serde_json::to_string(&skipped)?),
        ]);
        let options = SinkOptions {
            compression: settings.compression,
            chunk_size: settings.chunk_size_kib * 1024,
            flush_interval: (settings.flush_interval_s > 0.0)
                .then(|| Duration::from_secs_f64(settings.flush_interval_s)),
            queue: settings.queue_messages,
            json_mirror: settings.json_mirror,
            foxglove_channels: settings.foxglove_channels,
        };
        let ros2_dir = settings.ros2.as_ref().map(|r| r.path(&ctx.out_dir));
        Ok(Self {
            counts: vec![Counts::default(); taps.len()],
            channel,
            to_ros2,
            ros2: None,
            ros2_dir,
            earlier_ros2_parts: vec![],
            settings,
            path,
            sink: None,
            to_create: Some((options, metadata)),
            earlier_parts: vec![],
            topics,
            taps,
            skipped,
            last_seq: HashMap::new(),
            first_receive: None,
            last_receive: None,
            started: Instant::now(),
            written: 0,
        })
    }

    fn end_after(&self) -> EndAfter {
        if self.settings.end_after.is_empty() {
            EndAfter::Itself // records until it is stopped
        } else {
            EndAfter::All(self.settings.end_after.clone())
        }
    }

    fn tick(&self) -> Option<Duration> {
        Some(Duration::from_millis(250))
    }

    /// The killed instance's file is kept under another name, not overwritten.
    fn restore(&mut self, _restart: Restart) -> Result<usize, StageError> {
        if self.path.exists() {
            let stem = self.path.file_stem().and_then(|s| s.to_str()).unwrap_or("recording").to_string();
            let ext = self.path.extension().and_then(|s| s.to_str()).unwrap_or("mcap").to_string();
            let part = (1..)
                .map(|k| self.path.with_file_name(format!("{stem}.part{k}.{ext}")))
                .find(|p| !p.exists())
                .expect("some part number is free");
            std::fs::rename(&self.path, &part)?;
            tracing::warn!(
                file = %part.display(),
                "restarted: the killed instance's recording is kept as {} (cut short at its last complete chunk; \
                 `mcap recover` reads it); the rest of the run goes to {}",
                part.display(),
                self.path.display()
            );
            self.earlier_parts.push(part.display().to_string());
        }
        if let Some(dir) = self.ros2_dir.as_ref()
            && let ros2_interop::NewBag::KeptKilledInstance { part } = ros2_interop::prepare_bag_dir(dir, true)
                .map_err(|e| {
                    StageError::stage(crate::RecorderError::Message {
                        service: dir.display().to_string(),
                        what: e.to_string(),
                    })
                })?
        {
            tracing::warn!(dir = %part.display(), "restarted: the killed instance's ROS 2 bag is kept as {}", part.display());
            self.earlier_ros2_parts.push(part.display().to_string());
        }
        Ok(0)
    }

    fn step(&mut self, _rt: &mut Runtime, _wake: Wake, _inputs_ended: bool) -> Result<Step, StageError> {
        self.create()?;
        self.drain()?;
        Ok(Step::Idle)
    }

    /// `None` when the recorder never opened its file (nothing to report).
    type Summary = Option<RecorderPart>;

    fn finish(&mut self, rt: &mut Runtime, ending: Ending) -> Result<Self::Summary, StageError> {
        let why = match ending {
            Ending::EndOfStream => "end of stream",
            Ending::Stopped => "stopped",
        };
        self.create()?;
        if ending == Ending::Stopped
            && let Err(e) = self.drain()
        {
            tracing::warn!("last drain: {e:#}");
        }
        let ros2 = match self.ros2.take().map(|s| s.finish()).transpose()? {
            Some(r) => {
                if r.undecodable > 0 {
                    tracing::warn!(
                        undecodable = r.undecodable,
                        "ROS 2 bag: messages not of their service's type were left out"
                    );
                }
                tracing::info!(dir = %r.dir.display(), messages = r.messages.values().sum::<u64>(), "ROS 2 bag written");
                Some(Ros2BagSummary { report: r, earlier_parts: self.earlier_ros2_parts.clone() })
            }
            None => None,
        };
        let Some(sink) = self.sink.take() else { return Ok(None) };
        let counts: BTreeMap<String, String> = self
            .taps
            .iter()
            .zip(&self.counts)
            .map(|(t, c)| (t.service().to_string(), format!("received={} missed={}", c.received, c.missed)))
            .collect();
        sink.metadata("recorder_counts", counts)?;
        let r = sink.finish()?;
        let total: u64 = r.messages.values().sum();
        self.written = total;
        let active_s = match (self.first_receive, self.last_receive) {
            (Some(a), Some(b)) => (b - a).as_secs_f64(),
            _ => 0.0,
        };
        let missed: u64 = self.counts.iter().map(|c| c.missed).sum();
        tracing::info!(
            file = %self.path.display(),
            messages = total,
            missed,
            file_mb = r.file_bytes as f64 / 1e6,
            "recording written ({why}): {:.0} messages/s over {active_s:.1} s",
            total as f64 / active_s.max(1e-9)
        );
        let per_topic = |f: fn(&Counts) -> u64| -> BTreeMap<String, u64> {
            self.taps.iter().zip(&self.counts).map(|(t, c)| (t.service().to_string(), f(c))).collect()
        };
        // Under `recorder` (one recorder per run, as before) and under `recorders.<name>`: with
        // several recorders in a run the first is merged from all of them, the second is each one's.
        let part = RecordingSummary {
            file: self.path.display().to_string(),
            earlier_parts: self.earlier_parts.clone(),
            ended_by: why.to_string(),
            file_bytes: r.file_bytes,
            chunks: r.chunks,
            messages: r.messages,
            message_bytes: r.bytes,
            received: per_topic(|c| c.received),
            missed: per_topic(|c| c.missed),
            not_recorded: self.skipped.clone(),
            active_s,
            messages_per_s: total as f64 / active_s.max(1e-9),
            max_queued: r.max_queued,
            foxglove_messages: r.foxglove_messages,
            wall_s: self.started.elapsed().as_secs_f64(),
            ros2_bag: ros2,
        };
        Ok(Some(RecorderPart { recorder: part.clone(), recorders: BTreeMap::from([(rt.name().to_string(), part)]) }))
    }

    fn end_of_stream(&self) -> (u64, u64) {
        (self.written.saturating_sub(1), self.written)
    }

    fn sends_end_of_stream(&self) -> bool {
        self.settings.send_end_of_stream
    }
}
