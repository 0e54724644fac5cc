//! `fusion`: subscribes the synced pairs, the buoy fixes and the SLAM landmark maps; publishes
//! the fused global pose per SLAM pose on `pipeline/fusion/pose`, asks the SLAM process for a new
//! local map when camera and buoy stop overlapping, and at the end publishes the global map on
//! `pipeline/fusion/map` and writes the globally consistent path, the map, the transforms, the
//! accuracy and a plot. See the library docs.

use std::collections::BTreeSet;
use std::process::ExitCode;
use std::time::Duration;

use clap::Parser;
use fusion::engine::{Fusion, Source};
use fusion_process::journal::{Entry, Journal};
use fusion_process::{FusionSettings, RunLog, fix_from_wire, landmark_from_wire, pair_from_wire, write_outputs};
use pipeline_runtime::{Flow, ProcessArgs, Runtime};
use shared_types::services::{
    BUOY_FIX, COMMAND, END_OF_STREAM, FUSION_MAP, FUSION_POSE, HEADING, SLAM_LANDMARKS, SYNC_PAIR,
};
use shared_types::*;

fn flags(s: Source) -> u32 {
    match s {
        Source::Fused => FUSED_WITH_BUOY,
        Source::CameraOnly => FUSED_CAMERA_ONLY,
        Source::BuoyOnly => FUSED_BUOY_ONLY,
    }
}

fn count(log: &mut RunLog, reason: &str) {
    *log.invalid.entry(reason.to_string()).or_default() += 1;
}

fn run(args: &ProcessArgs) -> anyhow::Result<pipeline_runtime::StopReason> {
    let (ctx, mut rt) = Runtime::start(args)?;
    let settings: FusionSettings = ctx.settings()?;
    let mut engine =
        Fusion::new(settings.fusion.clone()).map_err(|p| anyhow::anyhow!("invalid fusion settings: {p:?}"))?;
    let pairs = rt.input::<SyncedPair, MsgHeader>(SYNC_PAIR)?;
    let fixes = rt.input::<BuoyFix, MsgHeader>(BUOY_FIX)?;
    let landmarks = rt.input::<[Landmark], LandmarkMapHeader>(SLAM_LANDMARKS)?;
    let headings = rt.input::<HeadingReading, MsgHeader>(HEADING)?;
    let eos = rt.input::<EndOfStream, MsgHeader>(END_OF_STREAM)?;
    let mut pose_out = rt.output::<FusedPose, MsgHeader>(FUSION_POSE)?;
    let mut map_out = rt.output_slice::<Landmark, LandmarkMapHeader>(FUSION_MAP, 4096)?;
    let mut commands = rt.output::<ControlCommand, MsgHeader>(COMMAND)?;
    let out_dir = ctx.out_dir.clone();
    let name = ctx.name.clone();
    let mut ended: BTreeSet<String> = BTreeSet::new();
    let mut log = RunLog::default();
    let mut done = false;
    let mut statuses: std::collections::BTreeMap<u32, std::mem::Discriminant<fusion::engine::SegmentStatus>> =
        Default::default();
    // A restarted instance replays what the killed one had taken into the new engine; a first
    // instance starts empty (whatever an earlier run left in the output directory).
    let journal_path = Journal::path(&ctx.out_dir, &ctx.name);
    let restarted = pipeline_runtime::restart::is_restart();
    let restored = if restarted { Journal::read(&journal_path)? } else { None };
    let mut journal = Journal::open(&journal_path, restored.as_ref())?;
    if let Some(r) = restored {
        for e in r.entries.iter().cloned() {
            match e {
                Entry::Fix(f) => engine.push_fix(f).map_err(|e| anyhow::anyhow!("journalled fix: {e}"))?,
                Entry::Heading(h) => engine.push_heading(h).map_err(|e| anyhow::anyhow!("journalled heading: {e}"))?,
                Entry::Pair(p) => {
                    let (t_s, buoy) = (p.t_s, p.buoy_m);
                    if let Ok(out) = engine.push_pair(*p) {
                        log.buoy.push((t_s, buoy));
                        log.live.push((out.t_s, out.world_from_body));
                        log.live_sources.add(out.source);
                        log.segment_requests += u64::from(out.request_new_segment);
                    }
                }
            }
        }
        for (segment, ls) in r.landmarks.iter().cloned() {
            engine.set_landmarks(segment, ls);
        }
        tracing::info!(
            inputs = r.entries.len(),
            local_maps = r.landmarks.len(),
            ignored_lines = r.ignored_lines,
            "restarted: replayed the killed instance's inputs"
        );
    }
    tracing::info!(slam = %settings.slam_process, end_after = ?settings.end_after, "fusion ready");
    let stop = rt.run(&mut engine, Some(Duration::from_millis(200)), |rt, engine, _| {
        if done {
            return Ok(Flow::Continue);
        }
        ended.extend(rt.ended_upstream(&eos)?); // before the data: see Runtime::ended_upstream
        let inputs_ended = settings.end_after.iter().all(|n| ended.contains(n));
        // Fixes and maps first, so that a pair sees every fix that arrived with it.
        while let Some(s) = fixes.receive()? {
            let fix = fix_from_wire(s.user_header(), s.payload());
            if engine.push_fix(fix).is_err() {
                count(&mut log, "buoy fix with NaN");
            } else {
                journal.push(&Entry::Fix(fix));
            }
        }
        while let Some(s) = headings.receive()? {
            let h = s.payload();
            let reading = fusion::engine::HeadingInput {
                t_s: s.user_header().stamp_ns as f64 / 1e9,
                yaw_rad: h.yaw_rad,
                sigma_rad: h.sigma_rad,
            };
            if engine.push_heading(reading).is_err() {
                count(&mut log, "heading with NaN or sigma <= 0");
            } else {
                journal.push(&Entry::Heading(reading));
            }
        }
        while let Some(s) = landmarks.receive()? {
            let h = s.user_header();
            let ls: Vec<_> = s.payload().iter().filter_map(landmark_from_wire).collect();
            if ls.len() < s.payload().len() {
                count(&mut log, "landmark with NaN");
            }
            journal.landmarks(h.segment_id, &ls)?;
            engine.set_landmarks(h.segment_id, ls);
        }
        while let Some(s) = pairs.receive()? {
            let h = *s.user_header();
            let pair = pair_from_wire(&h, s.payload());
            let buoy = pair.buoy_m;
            let t_s = pair.t_s;
            journal.push(&Entry::Pair(Box::new(pair.clone())));
            let out = match engine.push_pair(pair) {
                Ok(o) => o,
                Err(e) => {
                    count(&mut log, &format!("synced pair: {e}"));
                    continue;
                }
            };
            log.buoy.push((t_s, buoy));
            log.live.push((out.t_s, out.world_from_body));
            log.live_sources.add(out.source);
            // Journalled before publishing: a restarted instance replays what was journalled.
            journal.flush()?;
            if h.origin_ns > 0 {
                let now = pipeline_runtime::clock::monotonic_ns();
                log.stereo_to_fused_ms.push(now.saturating_sub(h.origin_ns) as f64 / 1e6);
            }
            pose_out.send_value(
                MsgHeader { stamp_ns: h.stamp_ns, origin_ns: h.origin_ns, ..Default::default() },
                FusedPose {
                    pose: PoseEstimate::from_nalgebra(&out.world_from_body, &out.covariance, out.segment, FRAME_WORLD),
                    flags: flags(out.source),
                    _reserved: 0,
                },
            )?;
            if let Some(seg) = engine.segment(out.segment) {
                // Log changes of kind (waiting, degenerate, aligned), not every new fix count.
                let kind = std::mem::discriminant(&seg.status);
                if statuses.get(&out.segment) != Some(&kind) {
                    tracing::info!(segment = out.segment, "local map: {:?}", seg.status);
                    statuses.insert(out.segment, kind);
                }
            }
            if out.request_new_segment {
                log.segment_requests += 1;
                tracing::info!(
                    segment = out.segment,
                    mahalanobis = out.mahalanobis,
                    "camera and buoy estimates stopped overlapping: asking {} for a new local map",
                    settings.slam_process
                );
                commands.send_value(
                    MsgHeader { stamp_ns: h.stamp_ns, origin_ns: h.origin_ns, ..Default::default() },
                    ControlCommand {
                        target: name32(&settings.slam_process),
                        command: COMMAND_NEW_SEGMENT,
                        _reserved: 0,
                        arg: out.segment as u64,
                    },
                )?;
            }
        }
        journal.flush()?;
        if inputs_ended {
            let result = engine.finish();
            let map = &result.global_map;
            let mut s = map_out.loan_slice_uninit(map.len())?.write_from_fn(|i| {
                let l = &map[i];
                Landmark {
                    id: i as u64,
                    mean_m: l.mean_m.into(),
                    covariance_m2: convert::mat3_to_row_major(&l.cov_m2),
                    descriptor: l.descriptor.unwrap_or([0; 32]),
                    observation_count: l.observations,
                    segment_id: u32::MAX,
                }
            });
            let stamp = result.path.last().map_or(0, |o| (o.t_s * 1e9) as u64);
            *s.user_header_mut() = LandmarkMapHeader {
                msg: MsgHeader { stamp_ns: stamp, ..Default::default() },
                segment_id: u32::MAX,
                frame: FRAME_WORLD,
            };
            map_out.send(s)?;
            let part = write_outputs(&out_dir, &settings, engine, &result, &log)?;
            let path = out_dir.join("parts").join(format!("{name}.json"));
            std::fs::create_dir_all(path.parent().expect("parts dir"))?;
            std::fs::write(path, serde_json::to_vec_pretty(&part)?)?;
            rt.send_end_of_stream(pose_out.sent().saturating_sub(1), pose_out.sent())?;
            done = true;
        }
        Ok(Flow::Continue)
    })?;
    if !done {
        // Stopped by a signal before the end of stream: the consistent path and map so far.
        let result = engine.finish();
        let part = write_outputs(&out_dir, &settings, &engine, &result, &log)?;
        let path = out_dir.join("parts").join(format!("{name}.json"));
        std::fs::create_dir_all(path.parent().expect("parts dir"))?;
        std::fs::write(path, serde_json::to_vec_pretty(&part)?)?;
        tracing::info!(poses = result.path.len(), "stopped early: outputs written");
    }
    Ok(stop)
}

fn main() -> ExitCode {
    let args = ProcessArgs::parse();
    let _log = pipeline_runtime::logging::init(&args.name, args.log_format.unwrap_or_default());
    pipeline_runtime::exit_code(&run(&args))
}
