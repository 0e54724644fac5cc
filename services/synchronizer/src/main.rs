//! `synchronizer`: subscribes the SLAM pose and the buoy fixes and publishes, for each SLAM pose,
//! a `SyncedPair` on `pipeline/sync/pair` with the buoy position interpolated to the pose's stamp
//! (SPEC §5.1). At the end it writes its counts and the added latency into summary.json. See the
//! library docs.

use std::collections::BTreeSet;
use std::process::ExitCode;
use std::time::{Duration, Instant};

use clap::Parser;
use pipeline_runtime::{Flow, ProcessArgs, Runtime};
use shared_types::services::{BUOY_FIX, END_OF_STREAM, SLAM_POSE, SYNC_PAIR};
use shared_types::*;
use synchronizer_process::{SyncState, SynchronizerSettings};

fn percentile(sorted: &[f64], q: f64) -> f64 {
    sorted.get(((sorted.len() as f64 - 1.0) * q).round() as usize).copied().unwrap_or(f64::NAN)
}

fn finish(
    st: &SyncState,
    settings: &SynchronizerSettings,
    out_dir: &std::path::Path,
    name: &str,
) -> anyhow::Result<()> {
    let mut ms: Vec<f64> = st.added_latency_s.iter().map(|s| s * 1e3).collect();
    ms.sort_by(f64::total_cmp);
    let c = st.synchronizer().counters();
    let part = serde_json::json!({ "synchronizer": {
        "pairs": ms.len(),
        "poses": st.stats,
        "fixes": { "inserted": c.inserted, "out_of_order": c.out_of_order, "duplicates": c.duplicates,
                   "restarts": c.restarts, "dropped": c.dropped },
        "max_latency_ms": settings.sync.max_latency_s * 1e3,
        "added_latency_ms": { "p50": percentile(&ms, 0.5), "p99": percentile(&ms, 0.99), "max": percentile(&ms, 1.0) },
    }});
    tracing::info!(
        pairs = ms.len(),
        extrapolated = st.stats.extrapolated,
        unavailable = st.stats.unavailable,
        "added latency p50 {:.2} ms, max {:.2} ms (bound {:.0} ms)",
        percentile(&ms, 0.5),
        percentile(&ms, 1.0),
        settings.sync.max_latency_s * 1e3
    );
    let path = out_dir.join("parts").join(format!("{name}.json"));
    std::fs::create_dir_all(path.parent().expect("parts dir"))?;
    std::fs::write(path, serde_json::to_vec_pretty(&part)?)?;
    Ok(())
}

fn run(args: &ProcessArgs) -> anyhow::Result<pipeline_runtime::StopReason> {
    let (ctx, mut rt) = Runtime::start(args)?;
    let settings: SynchronizerSettings = ctx.settings()?;
    let mut st = SyncState::new(&settings).map_err(|p| anyhow::anyhow!("invalid synchronizer settings: {p:?}"))?;
    let poses = rt.input::<PoseEstimate, MsgHeader>(SLAM_POSE)?;
    let fixes = rt.input::<BuoyFix, MsgHeader>(BUOY_FIX)?;
    let eos = rt.input::<EndOfStream, MsgHeader>(END_OF_STREAM)?;
    let mut pairs = rt.output::<SyncedPair, MsgHeader>(SYNC_PAIR)?;
    let out_dir = ctx.out_dir.clone();
    let name = ctx.name.clone();
    let mut ended: BTreeSet<String> = BTreeSet::new();
    let mut done = false;
    tracing::info!(max_latency_s = settings.sync.max_latency_s, end_after = ?settings.end_after, "synchronizer ready");
    let stop = rt.run(&mut st, Some(Duration::from_millis(100)), |rt, st, _| {
        if done {
            return Ok(Flow::Continue);
        }
        ended.extend(rt.ended_upstream(&eos)?); // before the data: see Runtime::ended_upstream
        let inputs_ended = if settings.end_after.is_empty() {
            !ended.is_empty()
        } else {
            settings.end_after.iter().all(|n| ended.contains(n))
        };
        // Fixes first, so that a pose and the fix that brackets it in one wake-up are paired.
        while let Some(s) = fixes.receive()? {
            st.push_fix(s.user_header(), s.payload());
        }
        let now = Instant::now();
        while let Some(s) = poses.receive()? {
            st.push_pose(*s.user_header(), *s.payload(), now);
        }
        for p in st.step(Instant::now(), inputs_ended) {
            let b = &p.buoy;
            pairs.send_value(
                MsgHeader { stamp_ns: p.header.stamp_ns, origin_ns: p.header.origin_ns, ..Default::default() },
                SyncedPair {
                    slam: p.pose,
                    buoy_position_m: b.position_m.into(),
                    buoy_covariance_m2: convert::mat3_to_row_major(&b.covariance_m2),
                    newest_fix_stamp_ns: (b.newest_fix_s * 1e9).round().max(0.0) as u64,
                    flags: b.flags.bits(),
                    fixes_used: b.fixes_used as u32,
                },
            )?;
        }
        if let Some(deadline) = st.next_deadline() {
            rt.wake_at(deadline);
        }
        if inputs_ended && st.pending.is_empty() {
            finish(st, &settings, &out_dir, &name)?;
            rt.send_end_of_stream(pairs.sent().saturating_sub(1), pairs.sent())?;
            done = true;
        }
        Ok(Flow::Continue)
    })?;
    if !done {
        // Stopped by a signal before the end of stream: write the counts so far.
        finish(&st, &settings, &out_dir, &name)?;
    }
    Ok(stop)
}

fn main() -> ExitCode {
    let args = ProcessArgs::parse();
    let _log = pipeline_runtime::logging::init(&args.name, args.log_format.unwrap_or_default());
    pipeline_runtime::exit_code(&run(&args))
}
