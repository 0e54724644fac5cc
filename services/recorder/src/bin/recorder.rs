//! `recorder`: subscribes the configured services with the contract's QoS and writes every
//! message it receives to `<out>/<file>` (MCAP): log_time = receive time, publish_time = the
//! message's `publish_ns`, data = the user header's bytes followed by the payload's bytes. It
//! counts sequence gaps per publisher (messages it missed), ends after the `end_after` processes
//! have ended (or on SIGTERM/SIGINT, after a last drain) and always leaves a complete file.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::process::ExitCode;
use std::time::{Duration, Instant};

use pipeline_runtime::{Flow, ProcessArgs, Runtime, StopReason, monotonic_ns};
use recorder_stage::{McapSink, RecorderSettings, SinkOptions, Tap, Topic};
use shared_types::services::END_OF_STREAM;
use shared_types::{EndOfStream, WireType, name_from32};

/// Per-topic counters.
#[derive(Default)]
struct Counts {
    received: u64,
    missed: u64,
}

struct Recorder {
    sink: Option<McapSink>,
    taps: Vec<(usize, Box<dyn Tap>)>,
    counts: Vec<Counts>,
    last_seq: HashMap<(usize, u128), u64>,
    ended: BTreeSet<String>,
    after_end: u64,
    first_receive: Option<Instant>,
    last_receive: Option<Instant>,
}

impl Recorder {
    /// Drains every tap (end of stream first: see `Runtime::ended_upstream`) into the sink.
    fn drain(&mut self, own_name: &str) -> anyhow::Result<usize> {
        let mut total = 0;
        let Self { sink, taps, counts, last_seq, ended, after_end, .. } = self;
        for (index, tap) in taps.iter() {
            let index = *index;
            total += tap.drain(&mut |r| {
                let c = &mut counts[index];
                c.received += 1;
                if let Some(last) = last_seq.insert((index, r.publisher), r.msg.seq)
                    && r.msg.seq > last + 1
                {
                    c.missed += r.msg.seq - last - 1;
                }
                if tap.service() == END_OF_STREAM
                    && let Some(eos) = EndOfStream::from_bytes(r.payload)
                {
                    let from = name_from32(&eos.process);
                    if from != own_name {
                        ended.insert(from);
                    }
                }
                let Some(sink) = sink.as_ref() else {
                    *after_end += 1;
                    return Ok(());
                };
                let mut data = Vec::with_capacity(r.header.len() + r.payload.len());
                data.extend_from_slice(r.header);
                data.extend_from_slice(r.payload);
                sink.write(index, monotonic_ns(), r.msg.publish_ns, data)
            })?;
        }
        if total > 0 {
            let now = Instant::now();
            self.first_receive.get_or_insert(now);
            self.last_receive = Some(now);
        }
        Ok(total)
    }
}

fn run(args: &ProcessArgs) -> anyhow::Result<StopReason> {
    let (ctx, mut rt) = Runtime::start(args)?;
    let settings: RecorderSettings = ctx.settings()?;
    let wanted = settings.topics();
    let mut topics: Vec<&'static Topic> = vec![];
    let mut taps = vec![];
    let mut skipped = BTreeMap::new();
    // End of stream first, so that a wake-up drains it before the data (see Runtime::ended_upstream).
    let mut order: Vec<&'static Topic> = wanted.iter().copied().filter(|t| t.service == END_OF_STREAM).collect();
    order.extend(wanted.iter().copied().filter(|t| t.service != END_OF_STREAM));
    for t in order {
        match t.tap(&mut rt) {
            Ok(tap) => {
                taps.push((topics.len(), tap));
                topics.push(t);
            }
            Err(e) => {
                tracing::warn!(service = t.service, "not recorded: {e}");
                skipped.insert(t.service.to_string(), e.to_string());
            }
        }
    }
    // Without end of stream among the recorded topics, `end_after` still needs to see it.
    let eos_side = if !settings.end_after.is_empty() && !topics.iter().any(|t| t.service == END_OF_STREAM) {
        Some(rt.input::<EndOfStream, shared_types::MsgHeader>(END_OF_STREAM)?)
    } else {
        None
    };
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
        flush_interval: (settings.flush_interval_s > 0.0).then(|| Duration::from_secs_f64(settings.flush_interval_s)),
        queue: settings.queue_messages,
        json_mirror: settings.json_mirror,
    };
    let sink = McapSink::create(&path, &topics, &options, metadata)?;
    tracing::info!(file = %path.display(), topics = topics.len(), not_recorded = skipped.len(), "recording");
    let mut st = Recorder {
        sink: Some(sink),
        taps,
        counts: topics.iter().map(|_| Counts::default()).collect(),
        last_seq: HashMap::new(),
        ended: BTreeSet::new(),
        after_end: 0,
        first_receive: None,
        last_receive: None,
    };
    let name = ctx.name.clone();
    let started = Instant::now();
    let finish = |st: &mut Recorder, why: &str| -> anyhow::Result<u64> {
        let Some(sink) = st.sink.take() else { return Ok(0) };
        let counts: BTreeMap<String, String> = topics
            .iter()
            .zip(&st.counts)
            .map(|(t, c)| (t.service.to_string(), format!("received={} missed={}", c.received, c.missed)))
            .collect();
        sink.metadata("recorder_counts", counts)?;
        let r = sink.finish()?;
        let total: u64 = r.messages.values().sum();
        let active_s = match (st.first_receive, st.last_receive) {
            (Some(a), Some(b)) => (b - a).as_secs_f64(),
            _ => 0.0,
        };
        let missed: u64 = st.counts.iter().map(|c| c.missed).sum();
        tracing::info!(
            file = %path.display(),
            messages = total,
            missed,
            file_mb = r.file_bytes as f64 / 1e6,
            "recording written ({why}): {:.0} messages/s over {active_s:.1} s",
            total as f64 / active_s.max(1e-9)
        );
        let part = serde_json::json!({ "recorder": {
            "file": path.display().to_string(),
            "ended_by": why,
            "file_bytes": r.file_bytes,
            "chunks": r.chunks,
            "messages": r.messages,
            "message_bytes": r.bytes,
            "received": topics.iter().zip(&st.counts).map(|(t, c)| (t.service, c.received)).collect::<BTreeMap<_, _>>(),
            "missed": topics.iter().zip(&st.counts).map(|(t, c)| (t.service, c.missed)).collect::<BTreeMap<_, _>>(),
            "not_recorded": skipped,
            "active_s": active_s,
            "messages_per_s": total as f64 / active_s.max(1e-9),
            "max_queued": r.max_queued,
            "wall_s": started.elapsed().as_secs_f64(),
        }});
        let part_path = ctx.summary_part_path();
        if let Some(dir) = part_path.parent() {
            std::fs::create_dir_all(dir)?;
        }
        std::fs::write(part_path, serde_json::to_vec_pretty(&part)?)?;
        Ok(total)
    };
    let end_after: BTreeSet<String> = settings.end_after.iter().cloned().collect();
    let stop = rt.run(&mut st, Some(Duration::from_millis(250)), |rt, st, _| {
        if let Some(eos) = &eos_side {
            st.ended.extend(rt.ended_upstream(eos)?);
        }
        st.drain(&name)?;
        if st.sink.is_some() && !end_after.is_empty() && end_after.is_subset(&st.ended) {
            let n = finish(st, "end of stream")?;
            if settings.send_end_of_stream {
                rt.send_end_of_stream(n.saturating_sub(1), n)?;
            }
        }
        Ok(Flow::Continue)
    });
    // Stopped by a signal (or the loop failed): drain what is queued and write a complete file.
    if st.sink.is_some() {
        if let Err(e) = st.drain(&name) {
            tracing::warn!("last drain: {e:#}");
        }
        let why = match &stop {
            Ok(StopReason::Signal(s)) => format!("signal {s}"),
            Ok(StopReason::Finished) => "finished".into(),
            Err(e) => format!("error: {e:#}"),
        };
        finish(&mut st, &why)?;
    }
    if st.after_end > 0 {
        tracing::info!(messages = st.after_end, "received after the recording ended (not recorded)");
    }
    stop
}

fn main() -> ExitCode {
    pipeline_runtime::process_main::<recorder_stage::RecorderSettings>(run)
}
