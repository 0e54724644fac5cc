//! The `replayer` process's stage: checks an MCAP recording, then publishes the recorded
//! messages of the selected topics with the contract's QoS in their original publish order, paced as recorded (times a
//! speed factor) or as fast as possible with back-pressure, and sends end of stream after the
//! last one. Payloads and user headers go out bit for bit; `seq`, `origin_ns` and `publish_ns`
//! are stamped anew by the publishing runtime (the message enters this pipeline now).

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::Path;
use std::time::{Duration, Instant};

use crate::summary::{ReplayerPart, ReplayerSummary};
use crate::{Emit, Replay, Replayed, ReplayerSettings, ScanReport, Selection, scan, topic};
use pipeline_runtime::stage::{EndAfter, Ending, Stage, Step};
use pipeline_runtime::{Delivery, ProcessContext, Runtime, StageError, Wake};
use shared_types::services::service_spec;

/// The replayer's stage: the recording it reads, an emitter per selected topic, the pacing.
pub struct Replayer {
    replay: Replay,
    emitters: HashMap<&'static str, Box<dyn Emit>>,
    pending: Option<Replayed>,
    speed: f64,
    anchor: Option<(Instant, u64)>,
    publish_from: Instant,
    sent: BTreeMap<&'static str, u64>,
    undelivered: BTreeMap<&'static str, u64>,
    done: bool,
    started: Instant,
    settings: ReplayerSettings,
    path: std::path::PathBuf,
    report: ScanReport,
}

impl Replayer {
    /// Publishes every message that is due; asks to be woken for the next one.
    fn pump(&mut self, rt: &mut Runtime) -> Result<(), StageError> {
        if Instant::now() < self.publish_from {
            for e in self.emitters.values() {
                e.nudge()?;
            }
            rt.wake_at(self.publish_from.min(Instant::now() + Duration::from_millis(25)));
            return Ok(());
        }
        let batch_end = Instant::now() + Duration::from_millis(20);
        while !self.done {
            if self.pending.is_none() {
                self.pending = self.replay.next_message()?;
            }
            let Some(m) = self.pending.take() else {
                let total: u64 = self.sent.values().sum();
                tracing::info!(
                    messages = total,
                    "replay finished in {:.1} s (held back at most {} messages to restore the publish order)",
                    self.started.elapsed().as_secs_f64(),
                    self.replay.max_held
                );
                self.done = true;
                break;
            };
            if self.speed > 0.0 {
                let now = Instant::now();
                let (wall0, t0) = *self.anchor.get_or_insert((now, m.publish_time));
                let due = wall0 + Duration::from_secs_f64(m.publish_time.saturating_sub(t0) as f64 / 1e9 / self.speed);
                if due > now {
                    self.pending = Some(m);
                    rt.wake_at(due);
                    break;
                }
            }
            let service = m.topic.service;
            let emitter = self
                .emitters
                .get_mut(service)
                .ok_or_else(|| StageError::msg(format!("`{service}`: no publisher (internal)")))?;
            let (reached, registered) = emitter.emit(&m.data)?;
            *self.sent.entry(service).or_default() += 1;
            if reached < registered {
                *self.undelivered.entry(service).or_default() += (registered - reached) as u64;
            }
            if Instant::now() >= batch_end {
                rt.wake_at(Instant::now()); // let the loop publish heartbeats, then go on
                break;
            }
        }
        Ok(())
    }
}

impl Stage for Replayer {
    type Settings = ReplayerSettings;

    fn open(ctx: &ProcessContext, settings: ReplayerSettings, rt: &mut Runtime) -> Result<Self, StageError> {
        let config_dir = ctx.config.source.parent().unwrap_or(Path::new(".")).to_path_buf();
        let path = settings.path(&config_dir);
        // Ends of stream recorded from processes of this config are theirs to send again.
        let own: BTreeSet<String> = ctx.config.processes.keys().cloned().collect();
        let selection = Selection::new(&settings.topics, own);
        let (rank, report) = scan(&path, &selection)?;
        tracing::info!(file = %path.display(), messages = rank.len(), topics = ?report.selected, "recording checked");
        let delivery = if settings.speed > 0.0 {
            Delivery::DiscardWhenFull
        } else {
            Delivery::WaitWhenFull {
                max_wait: (settings.backpressure_max_wait_s > 0.0)
                    .then(|| Duration::from_secs_f64(settings.backpressure_max_wait_s)),
            }
        };
        let mut emitters = HashMap::new();
        for service in report.selected.keys() {
            let (Some(t), Some(spec)) = (topic(service), service_spec(service)) else { continue };
            emitters.insert(t.service, t.emitter(rt, &spec.qos, delivery)?);
        }
        let replay = Replay::new(&path, selection, rank)?;
        let st = Replayer {
            replay,
            emitters,
            pending: None,
            speed: settings.speed,
            anchor: None,
            publish_from: Instant::now() + Duration::from_secs_f64(settings.connect_grace_s),
            sent: BTreeMap::new(),
            undelivered: BTreeMap::new(),
            done: false,
            started: Instant::now(),
            settings,
            path,
            report,
        };
        rt.wake_at(Instant::now());
        Ok(st)
    }

    fn end_after(&self) -> EndAfter {
        EndAfter::Itself
    }

    fn tick(&self) -> Option<Duration> {
        Some(Duration::from_millis(500))
    }

    fn step(&mut self, rt: &mut Runtime, _wake: Wake, _inputs_ended: bool) -> Result<Step, StageError> {
        self.pump(rt)?;
        Ok(if self.done { Step::Done } else { Step::Idle })
    }

    type Summary = ReplayerPart;

    fn finish(&mut self, _rt: &mut Runtime, _ending: Ending) -> Result<Self::Summary, StageError> {
        let by_name = |m: &BTreeMap<&'static str, u64>| m.iter().map(|(k, n)| (k.to_string(), *n)).collect();
        let r = &self.report;
        Ok(ReplayerPart {
            replayer: ReplayerSummary {
                file: self.path.display().to_string(),
                speed: self.settings.speed,
                in_file: r.in_file.clone(),
                selected: r.selected.clone(),
                sent: by_name(&self.sent),
                undelivered: by_name(&self.undelivered),
                skipped_end_of_stream: r.skipped_end_of_stream.clone(),
                received_out_of_publish_order: r.reordered,
                max_held: self.replay.max_held,
                complete: self.done,
            },
        })
    }

    fn end_of_stream(&self) -> (u64, u64) {
        let total: u64 = self.sent.values().sum();
        (total.saturating_sub(1), total)
    }

    fn sends_end_of_stream(&self) -> bool {
        self.settings.send_end_of_stream
    }
}
