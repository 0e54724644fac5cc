//! `odometer`: the wiring of the example stage (see the library docs). Its odometry input, the
//! end of stream of whoever feeds it, and its summary part at the end (or on a stop).

use std::process::ExitCode;

use odometer::{Odometer, OdometerSettings};
use pipeline_runtime::{Flow, ProcessArgs, Runtime};
use shared_types::services::{END_OF_STREAM, ODOMETRY};
use shared_types::{EndOfStream, MsgHeader, OdometryInput};

fn run(args: &ProcessArgs) -> anyhow::Result<pipeline_runtime::StopReason> {
    let (ctx, mut rt) = Runtime::start(args)?;
    let settings: OdometerSettings = ctx.settings()?;
    let odometry = rt.input::<OdometryInput, MsgHeader>(ODOMETRY)?;
    let eos = rt.input::<EndOfStream, MsgHeader>(END_OF_STREAM)?;
    let mut odo = Odometer::default();
    let mut ended = false;
    let stop = rt.run(&mut odo, None, |rt, odo, _| {
        if ended {
            return Ok(Flow::Continue);
        }
        let upstream_ended = !rt.ended_upstream(&eos)?.is_empty(); // first: see Runtime::ended_upstream
        while let Some(s) = odometry.receive()? {
            let u = s.payload();
            if let Err(why) = odo.on_odometry(u.v_mps, u.dt_s, &settings) {
                tracing::warn!(seq = s.user_header().seq, "odometry dropped: {why}");
                odometry.count_dropped("implausible", 1);
            }
        }
        if upstream_ended {
            tracing::info!(distance_m = odo.distance_m, messages = odo.messages, "upstream ended");
            rt.send_end_of_stream(0, 0)?;
            ended = true;
        }
        Ok(Flow::Continue)
    })?;
    std::fs::create_dir_all(ctx.out_dir.join("parts"))?;
    std::fs::write(ctx.summary_part_path(), serde_json::to_vec_pretty(&odo.summary_part())?)?;
    Ok(stop)
}

fn main() -> ExitCode {
    pipeline_runtime::process_main::<OdometerSettings>(run)
}
