//! `replayer`: checks an MCAP recording, then publishes the recorded messages of the selected
//! topics with the contract's QoS in their original publish order, paced as recorded (times a
//! speed factor) or as fast as possible with back-pressure, and sends end of stream after the
//! last one. Payloads and user headers go out bit for bit; `seq`, `origin_ns` and `publish_ns`
//! are stamped anew by the publishing runtime (the message enters this pipeline now).

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::Path;
use std::process::ExitCode;
use std::time::{Duration, Instant};

use pipeline_runtime::{Delivery, Flow, ProcessArgs, Runtime, StopReason};
use recorder_stage::{Emit, Replay, Replayed, ReplayerSettings, Selection, scan, topic};
use shared_types::services::service_spec;

struct Replayer {
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
}

impl Replayer {
    /// Publishes every message that is due; asks to be woken for the next one.
    fn pump(&mut self, rt: &mut Runtime, send_eos: bool) -> anyhow::Result<()> {
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
                if send_eos {
                    rt.send_end_of_stream(total.saturating_sub(1), total)?;
                }
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
                .ok_or_else(|| anyhow::anyhow!("`{service}`: no publisher (internal)"))?;
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

fn run(args: &ProcessArgs) -> anyhow::Result<StopReason> {
    let (ctx, mut rt) = Runtime::start(args)?;
    let settings: ReplayerSettings = ctx.settings()?;
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
        emitters.insert(t.service, t.emitter(&mut rt, &spec.qos, delivery)?);
    }
    let replay = Replay::new(&path, selection, rank)?;
    let mut st = Replayer {
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
    };
    rt.wake_at(Instant::now());
    let send_eos = settings.send_end_of_stream;
    // After the end of stream the process stays up (its samples stay valid) until it is stopped.
    let stop = rt.run(&mut st, Some(Duration::from_millis(500)), |rt, st, _| {
        if !st.done {
            st.pump(rt, send_eos)?;
        }
        Ok(Flow::Continue)
    });
    let part = serde_json::json!({ "replayer": {
        "file": path.display().to_string(),
        "speed": settings.speed,
        "in_file": report.in_file,
        "selected": report.selected,
        "sent": st.sent,
        "undelivered": st.undelivered,
        "skipped_end_of_stream": report.skipped_end_of_stream,
        "received_out_of_publish_order": report.reordered,
        "max_held": st.replay.max_held,
        "complete": st.done,
    }});
    let part_path = ctx.summary_part_path();
    if let Some(dir) = part_path.parent() {
        std::fs::create_dir_all(dir)?;
    }
    std::fs::write(part_path, serde_json::to_vec_pretty(&part)?)?;
    stop
}

fn main() -> ExitCode {
    pipeline_runtime::process_main::<recorder_stage::ReplayerSettings>(run)
}
