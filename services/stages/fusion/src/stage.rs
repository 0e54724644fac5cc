//! Fusion as a [`Stage`]: its ports and journal around the [`Fusion`] engine. It ends after
//! every process in `end_after` has ended (default: the synchronizer, the buoy EKF and SLAM).

use pipeline_runtime::StageError;
use std::time::Duration;

use fusion::engine::{Fusion, Source};
use pipeline_runtime::stage::{EndAfter, Ending, Stage, Step};
use pipeline_runtime::{Input, Output, ProcessContext, Restart, Runtime, Wake};
use shared_types::services::{BUOY_FIX, COMMAND, FUSION_MAP, FUSION_POSE, HEADING, SLAM_LANDMARKS, SYNC_PAIR};
use shared_types::*;

use crate::journal::Entry;
use crate::{FusionSettings, RunLog, fix_from_wire, landmark_from_wire, pair_from_wire, write_outputs};

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

/// The `fusion` stage.
pub struct FusionStage {
    settings: FusionSettings,
    engine: Fusion,
    pairs: Input<SyncedPair, MsgHeader>,
    fixes: Input<BuoyFix, MsgHeader>,
    landmarks: Input<[Landmark], LandmarkMapHeader>,
    headings: Input<HeadingReading, MsgHeader>,
    pose_out: Output<FusedPose, MsgHeader>,
    map_out: Output<[Landmark], LandmarkMapHeader>,
    commands: Output<ControlCommand, MsgHeader>,
    log: RunLog,
    statuses: std::collections::BTreeMap<u32, std::mem::Discriminant<fusion::engine::SegmentStatus>>,
    out_dir: std::path::PathBuf,
    /// Stamps of the predicted poses whose refined pose has not come yet, oldest first.
    predicted_stamps: std::collections::VecDeque<u64>,
}

impl FusionStage {
    /// Takes the buoy fixes, the headings and the local maps' landmarks that came (journalled).
    fn take_fixes_headings_and_maps(&mut self, rt: &mut Runtime) -> Result<(), StageError> {
        let (engine, log) = (&mut self.engine, &mut self.log);
        while let Some(s) = self.fixes.receive()? {
            let fix = fix_from_wire(s.user_header(), s.payload());
            if engine.push_fix(fix).is_err() {
                count(log, "buoy fix with NaN");
            } else {
                crate::journal::record(rt.state(), &Entry::Fix(fix));
            }
        }
        while let Some(s) = self.headings.receive()? {
            let h = s.payload();
            let reading = fusion::engine::HeadingInput {
                t_s: s.user_header().stamp_ns as f64 / 1e9,
                yaw_rad: h.yaw_rad,
                sigma_rad: h.sigma_rad,
            };
            if engine.push_heading(reading).is_err() {
                count(log, "heading with NaN or sigma <= 0");
            } else {
                crate::journal::record(rt.state(), &Entry::Heading(reading));
            }
        }
        while let Some(s) = self.landmarks.receive()? {
            let h = s.user_header();
            let ls: Vec<_> = s.payload().iter().filter_map(landmark_from_wire).collect();
            if ls.len() < s.payload().len() {
                count(log, "landmark with NaN");
            }
            crate::journal::landmarks(rt.state(), h.segment_id, &ls)?;
            engine.set_landmarks(h.segment_id, ls);
        }
        Ok(())
    }

    /// A predicted pair: a first pose at once from the state as it is; the refined pair follows.
    /// Not journalled: it changes nothing.
    fn on_predicted_pair(
        &mut self,
        h: &MsgHeader,
        pair: &fusion::engine::PairInput,
        latency_ms: Option<f64>,
    ) -> Result<(), StageError> {
        let log = &mut self.log;
        let out = match self.engine.predict_pair(pair) {
            Ok(o) => o,
            Err(e) => {
                log.predicted_invalid += 1;
                count(log, &format!("predicted pair: {e}"));
                return Ok(());
            }
        };
        log.predicted.push((out.t_s, out.world_from_body));
        log.first.push((out.t_s, out.world_from_body));
        self.predicted_stamps.push_back(h.stamp_ns);
        log.stereo_to_first_fused_ms.extend(latency_ms);
        self.pose_out.send_value(
            MsgHeader { stamp_ns: h.stamp_ns, origin_ns: h.origin_ns, ..Default::default() },
            FusedPose {
                pose: PoseEstimate::from_nalgebra(&out.world_from_body, &out.covariance, out.segment, FRAME_WORLD),
                flags: flags(out.source) | FUSED_PREDICTED,
                _reserved: 0,
            },
        )?;
        Ok(())
    }

    /// A pair proper: journalled, fused, published (the first pose of its stamp unless one was
    /// predicted), and a new local map asked for when camera and buoy stopped overlapping.
    fn on_pair(
        &mut self,
        rt: &mut Runtime,
        h: &MsgHeader,
        pair: fusion::engine::PairInput,
        latency_ms: Option<f64>,
        now: u64,
    ) -> Result<(), StageError> {
        let stamps = &mut self.predicted_stamps;
        while stamps.front().is_some_and(|&t| t < h.stamp_ns) {
            stamps.pop_front();
        }
        let was_predicted = stamps.front() == Some(&h.stamp_ns);
        if was_predicted {
            stamps.pop_front();
        }
        let (buoy, buoy_cov, t_s) = (pair.buoy_m, pair.buoy_cov_m2, pair.t_s);
        crate::journal::record(rt.state(), &Entry::Pair(Box::new(pair.clone())));
        let log = &mut self.log;
        let out = match self.engine.push_pair(pair) {
            Ok(o) => o,
            Err(e) => {
                count(log, &format!("synced pair: {e}"));
                return Ok(());
            }
        };
        log.buoy.push((t_s, buoy));
        log.buoy_cov_m2.push(buoy_cov);
        log.live.push((out.t_s, out.world_from_body));
        log.live_position_cov_m2.push(out.covariance.fixed_view::<3, 3>(0, 0).into_owned());
        log.live_sources.add(out.source);
        if !was_predicted {
            log.first.push((out.t_s, out.world_from_body));
        }
        // Journalled before publishing: a restarted instance replays what was journalled.
        rt.state().flush()?;
        if let Some(ms) = latency_ms {
            let ms = ms + (pipeline_runtime::clock::monotonic_ns() - now) as f64 / 1e6;
            log.stereo_to_fused_ms.push(ms);
            if !was_predicted {
                log.stereo_to_first_fused_ms.push(ms);
            }
        }
        self.pose_out.send_value(
            MsgHeader { stamp_ns: h.stamp_ns, origin_ns: h.origin_ns, ..Default::default() },
            FusedPose {
                pose: PoseEstimate::from_nalgebra(&out.world_from_body, &out.covariance, out.segment, FRAME_WORLD),
                flags: flags(out.source) | FUSED_REFINED,
                _reserved: 0,
            },
        )?;
        if let Some(seg) = self.engine.segment(out.segment) {
            // Log changes of kind (waiting, degenerate, aligned), not every new fix count.
            let kind = std::mem::discriminant(&seg.status);
            if self.statuses.get(&out.segment) != Some(&kind) {
                if seg.prior_rejected {
                    tracing::warn!(
                        segment = out.segment,
                        "the fixes disagree with the transform carried over from the previous local map (or with \
                         the compass's level frame): aligned with the fixes alone"
                    );
                }
                tracing::info!(segment = out.segment, "local map: {:?}", seg.status);
                self.statuses.insert(out.segment, kind);
            }
        }
        if out.request_new_segment {
            self.log.segment_requests += 1;
            tracing::info!(
                segment = out.segment,
                mahalanobis = out.mahalanobis,
                "camera and buoy estimates stopped overlapping: asking {} for a new local map",
                self.settings.slam_process
            );
            self.commands.send_value(
                MsgHeader { stamp_ns: h.stamp_ns, origin_ns: h.origin_ns, ..Default::default() },
                ControlCommand {
                    target: name32(&self.settings.slam_process),
                    command: COMMAND_NEW_SEGMENT,
                    _reserved: 0,
                    arg: out.segment as u64,
                },
            )?;
        }
        Ok(())
    }
}

impl Stage for FusionStage {
    type Settings = FusionSettings;

    fn open(ctx: &ProcessContext, settings: FusionSettings, rt: &mut Runtime) -> Result<Self, StageError> {
        let engine =
            Fusion::new(settings.fusion.clone()).map_err(|p| StageError::Settings(format!("fusion: {p:?}")))?;
        let pairs = rt.input::<SyncedPair, MsgHeader>(SYNC_PAIR)?;
        let fixes = rt.input::<BuoyFix, MsgHeader>(BUOY_FIX)?;
        let landmarks = rt.input::<[Landmark], LandmarkMapHeader>(SLAM_LANDMARKS)?;
        let headings = rt.input::<HeadingReading, MsgHeader>(HEADING)?;
        let pose_out = rt.output::<FusedPose, MsgHeader>(FUSION_POSE)?;
        let map_out = rt.output_slice::<Landmark, LandmarkMapHeader>(FUSION_MAP, 4096)?;
        let commands = rt.output::<ControlCommand, MsgHeader>(COMMAND)?;
        tracing::info!(slam = %settings.slam_process, end_after = ?settings.end_after, "fusion ready");
        Ok(Self {
            settings,
            engine,
            pairs,
            fixes,
            landmarks,
            headings,
            pose_out,
            map_out,
            commands,
            log: RunLog::default(),
            statuses: Default::default(),
            out_dir: ctx.out_dir.clone(),
            predicted_stamps: Default::default(),
        })
    }

    fn end_after(&self) -> EndAfter {
        EndAfter::from_list(&self.settings.end_after)
    }

    fn tick(&self) -> Option<Duration> {
        Some(Duration::from_millis(200))
    }

    /// A restarted instance replays what the killed one had taken into the new engine (it is
    /// deterministic: back in the killed one's state); nothing is published during the replay.
    fn restore(&mut self, restart: Restart) -> Result<usize, StageError> {
        let r = crate::journal::read(&restart)?;
        let (engine, log) = (&mut self.engine, &mut self.log);
        for e in r.entries.iter().cloned() {
            match e {
                Entry::Fix(f) => engine.push_fix(f).map_err(|e| StageError::msg(format!("journalled fix: {e}")))?,
                Entry::Heading(h) => {
                    engine.push_heading(h).map_err(|e| StageError::msg(format!("journalled heading: {e}")))?
                }
                Entry::Pair(p) => {
                    let (t_s, buoy, buoy_cov) = (p.t_s, p.buoy_m, p.buoy_cov_m2);
                    if let Ok(out) = engine.push_pair(*p) {
                        log.buoy.push((t_s, buoy));
                        log.buoy_cov_m2.push(buoy_cov);
                        log.live.push((out.t_s, out.world_from_body));
                        log.live_position_cov_m2.push(out.covariance.fixed_view::<3, 3>(0, 0).into_owned());
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
            "restarted: replayed the killed instance's inputs"
        );
        Ok(r.lines)
    }

    fn step(&mut self, rt: &mut Runtime, _wake: Wake, _inputs_ended: bool) -> Result<Step, StageError> {
        // Fixes and maps first, so that a pair sees every fix that arrived with it.
        self.take_fixes_headings_and_maps(rt)?;
        loop {
            // The pair is copied out of shared memory: the sample goes back before the work.
            let Some((h, pair, predicted)) = self.pairs.receive()?.map(|s| {
                let h = *s.user_header();
                (h, pair_from_wire(&h, s.payload()), s.payload().flags & SYNC_PREDICTED != 0)
            }) else {
                break;
            };
            let now = pipeline_runtime::clock::monotonic_ns();
            let latency_ms = (h.origin_ns > 0).then(|| now.saturating_sub(h.origin_ns) as f64 / 1e6);
            if predicted {
                self.on_predicted_pair(&h, &pair, latency_ms)?;
            } else {
                self.on_pair(rt, &h, pair, latency_ms, now)?;
            }
        }
        Ok(Step::Idle)
    }

    type Summary = crate::summary::FusionPart;

    fn finish(&mut self, rt: &mut Runtime, ending: Ending) -> Result<Self::Summary, StageError> {
        let result = self.engine.finish();
        rt.keep_alive();
        if ending == Ending::EndOfStream {
            let map = &result.global_map;
            let mut s = self.map_out.loan_slice_uninit(map.len())?.write_from_fn(|i| {
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
            self.map_out.send(s)?;
        } else {
            tracing::info!(poses = result.path.len(), "stopped early: the consistent path and map so far");
        }
        write_outputs(&self.out_dir, &self.settings, &self.engine, &result, &self.log)
    }

    fn end_of_stream(&self) -> (u64, u64) {
        (self.pose_out.sent().saturating_sub(1), self.pose_out.sent())
    }
}
