//! `test_producer`: publishes deterministic point clouds of a configured size and rate on
//! `pipeline/sensors/cloud`, written in place into loaned shared memory; end of stream after
//! `frames` clouds; optionally crashes or stalls on purpose (see `testkit::ProducerSettings`).

use std::process::ExitCode;
use std::time::Duration;

use pipeline_runtime::{Flow, ProcessArgs, Runtime, monotonic_ns};
use shared_types::services::CLOUD;
use shared_types::{CloudHeader, CloudPoint, FRAME_SENSOR};
use testkit::{ProducerSettings, cloud_point};

fn run(args: &ProcessArgs) -> anyhow::Result<pipeline_runtime::StopReason> {
    let (ctx, mut rt) = Runtime::start(args)?;
    let settings: ProducerSettings = ctx.settings()?;
    let mut out = rt.output_slice::<CloudPoint, CloudHeader>(CLOUD, settings.points)?;
    let period = Duration::from_secs_f64(1.0 / settings.rate_hz);
    let mut done = false;
    rt.run(&mut out, Some(period), |rt, out, wake| {
        if !wake.tick || done {
            return Ok(Flow::Continue);
        }
        let seq = out.next_seq();
        if settings.abort_after_frames == Some(seq) {
            tracing::warn!(seq, "aborting on purpose (abort_after_frames)");
            std::process::abort();
        }
        if settings.stall_after_frames == Some(seq) {
            tracing::warn!(seq, "stalling on purpose (stall_after_frames)");
            loop {
                std::thread::sleep(Duration::from_secs(3600));
            }
        }
        let sample = out.loan_slice_uninit(settings.points)?;
        let mut sample = sample.write_from_fn(|i| cloud_point(seq, i));
        *sample.user_header_mut() = CloudHeader {
            msg: shared_types::MsgHeader { stamp_ns: monotonic_ns(), ..Default::default() },
            frame: FRAME_SENSOR,
            ..Default::default()
        };
        out.send(sample)?;
        if settings.frames > 0 {
            rt.set_progress(out.sent() as f64 / settings.frames as f64);
        }
        if settings.frames > 0 && out.sent() >= settings.frames {
            rt.send_end_of_stream(seq, out.sent())?;
            done = true; // stay alive (publisher memory stays valid) until stopped
        }
        Ok(Flow::Continue)
    })
}

fn main() -> ExitCode {
    pipeline_runtime::process_main::<testkit::ProducerSettings, _>(run)
}
