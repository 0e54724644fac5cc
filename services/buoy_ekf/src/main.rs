//! `buoy_ekf`: subscribes odometry, buoy ranges and pressure depth, runs the buoy EKF in stamp
//! order and publishes a `BuoyFix` per ranges message on `pipeline/buoy/fix`; at the end of the
//! stream writes `buoy_ekf.tum`, `dead_reckoning.tum` and, with a ground truth, `ate_m.buoy_ekf`
//! and `ate_m.dead_reckoning` into summary.json. See the library docs.

use std::process::ExitCode;
use std::time::{Duration, Instant};

use buoy::Mode;
use buoy_ekf_process::journal::Journal;
use buoy_ekf_process::{BuoyEkfSettings, BuoyState, ate_nearest, dead_reckoning, fix_pose};
use clap::Parser;
use nalgebra::Vector3;
use pipeline_runtime::{Flow, ProcessArgs, Runtime};
use shared_types::services::{BUOY_FIX, BUOY_RANGES, DEPTH, END_OF_STREAM, ODOMETRY};
use shared_types::*;

fn finish(
    st: &BuoyState,
    settings: &BuoyEkfSettings,
    out_dir: &std::path::Path,
    name: &str,
    fixes_sent: u64,
) -> anyhow::Result<()> {
    std::fs::create_dir_all(out_dir)?;
    let planar = settings.ekf.mode == Mode::Planar;
    let poses: Vec<_> = st.trajectory.iter().map(|(t, p, h)| (*t, fix_pose(p, *h))).collect();
    geometry::tum::write_tum(&out_dir.join("buoy_ekf.tum"), poses.iter().map(|(t, p)| (*t, p)))?;
    let counters = st.ekf().map(|e| e.counters().clone()).unwrap_or_default();
    let estimate = st.ekf().filter(|e| e.is_initialised()).and_then(|e| e.estimate().ok());
    let mut part = serde_json::json!({ "buoy_ekf": {
        "fixes": fixes_sent,
        "trajectory_samples": st.trajectory.len(),
        "ranges_accepted": counters.accepted,
        "ranges_rejected": counters.rejected,
        "recoveries": counters.recoveries,
        "depth_rejected": counters.depth_rejected,
        "ranges_waiting_for_initialisation": st.waiting,
        "per_buoy": counters.per_buoy.iter().map(|b| serde_json::json!({
            "id": b.id, "accepted": b.accepted, "rejected": b.rejected })).collect::<Vec<_>>(),
        "range_biases_m": estimate.as_ref().map(|e| e.biases.iter().map(|b| serde_json::json!({
            "buoy_id": b.buoy_id, "bias_m": b.bias_m, "sigma_m": b.sigma_m })).collect::<Vec<_>>()),
        "range_scale": estimate.as_ref().and_then(|e| e.range_scale).map(|s| s.0),
        "invalid_inputs": st.invalid,
        "filter_errors": st.filter_errors,
    }});
    let gt_path = out_dir.join(&settings.ground_truth);
    match geometry::tum::read_tum(&gt_path) {
        Ok(truth) if !truth.is_empty() => {
            let truth_p: Vec<(f64, Vector3<f64>)> = truth.iter().map(|(t, p)| (*t, p.translation.vector)).collect();
            let est: Vec<(f64, Vector3<f64>)> = st.trajectory.iter().map(|(t, p, _)| (*t, *p)).collect();
            let ate = ate_nearest(&est, &truth_p, planar);
            let mut ates = serde_json::json!({ "buoy_ekf": ate });
            if let Some((t0, u0)) = st.inputs.first() {
                // Dead reckoning from the ground-truth pose at the start of the first input.
                let start = buoy_ekf_process::nearest(&truth, t0 - u0.dt_s).copied().unwrap_or(truth[0].1);
                let dr = dead_reckoning(&start, &st.inputs);
                geometry::tum::write_tum(&out_dir.join("dead_reckoning.tum"), dr.iter().map(|(t, p)| (*t, p)))?;
                let dr_p: Vec<_> = dr.iter().map(|(t, p)| (*t, p.translation.vector)).collect();
                let dr_ate = ate_nearest(&dr_p, &truth_p, planar);
                ates["dead_reckoning"] = serde_json::json!(dr_ate);
                tracing::info!(
                    "ATE ({}, nearest stamp, every ground-truth row): buoy EKF {ate:.3} m, dead reckoning {dr_ate:.3} m",
                    if planar { "2-D" } else { "3-D" }
                );
            } else {
                tracing::info!("ATE (nearest stamp, every ground-truth row): buoy EKF {ate:.3} m");
            }
            part["ate_m"] = ates;
        }
        Ok(_) => tracing::info!("no accuracy evaluation: {} is empty", gt_path.display()),
        Err(e) => tracing::info!("no accuracy evaluation: {e}"),
    }
    let path = out_dir.join("parts").join(format!("{name}.json"));
    std::fs::create_dir_all(path.parent().expect("parts dir"))?;
    std::fs::write(path, serde_json::to_vec_pretty(&part)?)?;
    Ok(())
}

fn run(args: &ProcessArgs) -> anyhow::Result<pipeline_runtime::StopReason> {
    let (ctx, mut rt) = Runtime::start(args)?;
    let settings: BuoyEkfSettings = ctx.settings()?;
    let odometry = rt.input::<OdometryInput, MsgHeader>(ODOMETRY)?;
    let ranges = rt.input::<[BuoyRange], MsgHeader>(BUOY_RANGES)?;
    let depth = rt.input::<DepthReading, MsgHeader>(DEPTH)?;
    let eos = rt.input::<EndOfStream, MsgHeader>(END_OF_STREAM)?;
    let mut fixes = rt.output::<BuoyFix, MsgHeader>(BUOY_FIX)?;
    let mut st = BuoyState::new(settings.clone());
    // A restarted instance keeps the killed one's trajectory and inputs (the filter starts over);
    // a first instance starts empty (whatever an earlier run left in the output directory).
    let journal_path = Journal::path(&ctx.out_dir, &ctx.name);
    let restarted = pipeline_runtime::restart::is_restart();
    let restored = if restarted { Journal::read(&journal_path)? } else { None };
    let mut journal = Journal::open(&journal_path, restored.as_ref())?;
    if let Some(r) = restored {
        tracing::info!(
            samples = r.trajectory.len(),
            inputs = r.inputs.len(),
            ignored_lines = r.ignored_lines,
            "restarted: kept the killed instance's trajectory; the filter starts over"
        );
        st.trajectory = r.trajectory;
        st.inputs = r.inputs;
    }
    let mut journalled = (st.trajectory.len(), st.inputs.len());
    let out_dir = ctx.out_dir.clone();
    let name = ctx.name.clone();
    let mut done = false;
    let mut upstream_ended = false;
    tracing::info!(buoys = settings.ekf.buoys.len(), mode = ?settings.ekf.mode, odometry = settings.use_odometry, "buoy EKF ready");
    let mut was_initialised = false;
    let stop = rt.run(&mut st, Some(Duration::from_millis(100)), |rt, st, _| {
        if done {
            return Ok(Flow::Continue);
        }
        if !rt.ended_upstream(&eos)?.is_empty() {
            upstream_ended = true; // read before the data: see Runtime::ended_upstream
        }
        let now = Instant::now();
        while let Some(s) = odometry.receive()? {
            st.push_odometry(s.user_header().stamp_ns, s.payload());
        }
        while let Some(s) = ranges.receive()? {
            let h = s.user_header();
            st.push_ranges(h.stamp_ns, h.origin_ns, s.payload(), now);
        }
        while let Some(s) = depth.receive()? {
            st.push_depth(s.user_header().stamp_ns, s.payload());
        }
        let out = st.step(upstream_ended, now);
        // Journal before publishing: a restarted instance resumes from what was journalled.
        journal.append(&st.trajectory[journalled.0..], &st.inputs[journalled.1..])?;
        journalled = (st.trajectory.len(), st.inputs.len());
        for f in out {
            let e = &f.estimate;
            fixes.send_value(
                MsgHeader { stamp_ns: f.stamp_ns, origin_ns: f.origin_ns, ..Default::default() },
                BuoyFix {
                    position_m: e.position_m.into(),
                    covariance_m2: convert::mat3_to_row_major(&e.covariance_m2),
                    velocity_mps: e.velocity_mps.into(),
                    ranges_used: f.used,
                    ranges_rejected: f.rejected,
                },
            )?;
        }
        if !was_initialised && st.ekf().is_some_and(|e| e.is_initialised()) {
            was_initialised = true;
            if let Some(Ok(e)) = st.ekf().map(|e| e.estimate()) {
                tracing::info!(position_m = ?e.position_m.as_slice(), "initialised");
            }
        }
        if let Some(deadline) = st.next_deadline() {
            rt.wake_at(deadline);
        }
        if upstream_ended && st.pending() == 0 {
            finish(st, &settings, &out_dir, &name, fixes.sent())?;
            rt.send_end_of_stream(fixes.sent().saturating_sub(1), fixes.sent())?;
            done = true;
        }
        Ok(Flow::Continue)
    })?;
    if !done {
        // Stopped by a signal before the end of stream: write what there is.
        finish(&st, &settings, &out_dir, &name, fixes.sent())?;
        tracing::info!(fixes = fixes.sent(), "stopped early: outputs written");
    }
    Ok(stop)
}

fn main() -> ExitCode {
    let args = ProcessArgs::parse();
    let _log = pipeline_runtime::logging::init(&args.name, args.log_format.unwrap_or_default());
    pipeline_runtime::exit_code(&run(&args))
}
