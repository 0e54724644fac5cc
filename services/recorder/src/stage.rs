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
    topics: Vec<&'static Topic>,
    taps: Vec<Box<dyn Tap>>,
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
        let Self { sink, taps, counts, last_seq, .. } = self;
        let Some(sink) = sink.as_ref() else { return Ok(0) };
        let mut failed = None;
        for (index, tap) in taps.iter().enumerate() {
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
                    match sink.write(index, monotonic_ns(), r.msg.publish_ns, data) {
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
        let mut skipped = BTreeMap::new();
        for t in settings.topics() {
            match t.tap(rt) {
                Ok(tap) => {
                    taps.push(tap);
                    topics.push(t);
                }
                Err(e) => {
                    tracing::warn!(service = t.service, "not recorded: {e}");
                    skipped.insert(t.service.to_string(), e.to_string());
                }
            }
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
        Ok(Self {
            counts: vec![Counts::default(); topics.len()],
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
        Ok(0)
    }

    fn step(&mut self, _rt: &mut Runtime, _wake: Wake, _inputs_ended: bool) -> Result<Step, StageError> {
        self.create()?;
        self.drain()?;
        Ok(Step::Idle)
    }

    fn finish(&mut self, rt: &mut Runtime, ending: Ending) -> Result<serde_json::Value, StageError> {
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
        let Some(sink) = self.sink.take() else { return Ok(serde_json::json!({})) };
        let counts: BTreeMap<String, String> = self
            .topics
            .iter()
            .zip(&self.counts)
            .map(|(t, c)| (t.service.to_string(), format!("received={} missed={}", c.received, c.missed)))
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
        let per_topic = |f: fn(&Counts) -> u64| -> BTreeMap<&str, u64> {
            self.topics.iter().zip(&self.counts).map(|(t, c)| (t.service, f(c))).collect()
        };
        // Under `recorder` (one recorder per run, as before) and under `recorders.<name>`: with
        // several recorders in a run the first is merged from all of them, the second is each one's.
        let part = serde_json::json!({
            "file": self.path.display().to_string(),
            "earlier_parts": self.earlier_parts,
            "ended_by": why,
            "file_bytes": r.file_bytes,
            "chunks": r.chunks,
            "messages": r.messages,
            "message_bytes": r.bytes,
            "received": per_topic(|c| c.received),
            "missed": per_topic(|c| c.missed),
            "not_recorded": self.skipped,
            "active_s": active_s,
            "messages_per_s": total as f64 / active_s.max(1e-9),
            "max_queued": r.max_queued,
            "foxglove_messages": r.foxglove_messages,
            "wall_s": self.started.elapsed().as_secs_f64(),
        });
        Ok(serde_json::json!({ "recorder": part.clone(), "recorders": { rt.name(): part } }))
    }

    fn end_of_stream(&self) -> (u64, u64) {
        (self.written.saturating_sub(1), self.written)
    }

    fn sends_end_of_stream(&self) -> bool {
        self.settings.send_end_of_stream
    }
}
