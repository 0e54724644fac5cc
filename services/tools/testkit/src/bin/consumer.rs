//! `test_consumer`: receives clouds, verifies every point against the producer's formula,
//! records latency, forwards end of stream, and writes its counters to `parts/<name>.json`.

use std::process::ExitCode;

use pipeline_runtime::{Flow, ProcessArgs, Runtime};
use shared_types::services::{CLOUD, END_OF_STREAM, STEREO};
use shared_types::{CloudHeader, CloudPoint, EndOfStream, MsgHeader, StereoObservation};
use testkit::{ConsumerCounters, ConsumerSettings, verify_cloud};

fn write_part(path: &std::path::Path, counters: &ConsumerCounters) -> anyhow::Result<()> {
    std::fs::create_dir_all(path.parent().expect("part path has a parent"))?;
    std::fs::write(path, serde_json::to_vec_pretty(&testkit::ConsumerPart { test_consumer: counters.clone() })?)?;
    Ok(())
}

fn run(args: &ProcessArgs) -> anyhow::Result<pipeline_runtime::StopReason> {
    let (ctx, mut rt) = Runtime::start(args)?;
    let settings: ConsumerSettings = ctx.settings()?;
    let clouds = rt.input::<[CloudPoint], CloudHeader>(CLOUD)?;
    let eos = rt.input::<EndOfStream, MsgHeader>(END_OF_STREAM)?;
    let stereo =
        if settings.stereo_delay_ms > 0 { Some(rt.input::<[StereoObservation], MsgHeader>(STEREO)?) } else { None };
    let delay = std::time::Duration::from_millis(settings.stereo_delay_ms);
    let mut last_stereo: Option<u64> = None;
    let mut counters = ConsumerCounters::default();
    let part = ctx.summary_part_path();
    let mut pending_ends: Vec<String> = vec![];
    let result = rt.run(&mut counters, None, |rt, counters, _wake| {
        pending_ends.extend(rt.ended_upstream(&eos)?); // first: see Runtime::ended_upstream
        while let Some(s) = clouds.receive()? {
            let seq = s.user_header().msg.seq;
            if let Err(fault) = verify_cloud(counters, settings.expect_points, seq, s.payload()) {
                tracing::warn!(seq, ?fault, "cloud failed verification");
            }
        }
        if let Some(stereo) = &stereo {
            // One slow frame per wake-up: heartbeats go out between frames.
            if let Some(s) = stereo.receive()? {
                let seq = s.user_header().seq;
                counters.stereo_frames += 1;
                counters.stereo_missed += last_stereo.map_or(seq, |l| seq.saturating_sub(l + 1));
                last_stereo = Some(seq);
                drop(s);
                std::thread::sleep(delay);
                rt.wake_at(std::time::Instant::now());
                return Ok(Flow::Continue);
            }
        }
        for from in std::mem::take(&mut pending_ends) {
            counters.end_of_stream_seen += 1;
            tracing::info!(%from, frames_ok = counters.frames_ok, "end of stream from upstream");
            if settings.forward_end_of_stream {
                let last = counters.last_seq.unwrap_or(0);
                rt.send_end_of_stream(last, counters.frames_ok + counters.frames_bad)?;
            }
        }
        Ok(Flow::Continue)
    });
    write_part(&part, &counters)?;
    tracing::info!(?counters, "done");
    result
}

fn main() -> ExitCode {
    pipeline_runtime::process_main::<testkit::ConsumerSettings, _>(run)
}
