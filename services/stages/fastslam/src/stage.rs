//! FastSLAM as a [`Stage`]: its ports, journal and per-frame publishing around [`SlamState`].
//! It ends after the first upstream end of stream, once its own frame queue is empty.

use pipeline_runtime::StageError;
use std::time::{Duration, Instant};

use fastslam::frontend::RegistrationError;
use fastslam::{FastSlam, SegmentReason};
use pipeline_runtime::stage::{EndAfter, Ending, Stage, Step};
use pipeline_runtime::{Input, Output, ProcessContext, Restart, Runtime, Wake};
use shared_types::services::{COMMAND, ODOMETRY, SLAM_DIAGNOSTICS, SLAM_LANDMARKS, SLAM_PARTICLES, SLAM_POSE, STEREO};
use shared_types::*;

use crate::summary::{FastSlamPart, FrontendSummary, SegmentSummary, SlamAte, SlamNees, SlamSummary};
use crate::{FastSlamSettings, SlamState, frame_from_wire};
use pipeline_runtime::summary::{Percentiles, finite};

struct Outputs {
    pose: Output<PoseEstimate, MsgHeader>,
    particles: Output<[Particle], ParticleSetHeader>,
    landmarks: Output<[Landmark], LandmarkMapHeader>,
    diagnostics: Output<SlamDiagnostics, MsgHeader>,
}

/// Stereo frames taken from the service into the process's own queue at most.
const MAX_QUEUED_FRAMES: usize = 2;

fn header(stamp_ns: u64, origin_ns: u64) -> MsgHeader {
    MsgHeader { stamp_ns, origin_ns, ..Default::default() }
}

fn publish_landmarks(
    out: &mut Output<[Landmark], LandmarkMapHeader>,
    f: &FastSlam,
    stamp_ns: u64,
    origin_ns: u64,
) -> Result<(), StageError> {
    let map = f.best_map();
    let segment = f.segment();
    let mut s = out.loan_slice_uninit(map.len())?.write_from_fn(|i| {
        let (id, l) = map[i];
        Landmark {
            id: id as u64,
            mean_m: l.mean_m.into(),
            covariance_m2: convert::mat3_to_row_major(&l.cov_m2),
            descriptor: l.descriptor.unwrap_or([0; 32]),
            observation_count: l.hits,
            segment_id: segment,
        }
    });
    *s.user_header_mut() =
        LandmarkMapHeader { msg: header(stamp_ns, origin_ns), segment_id: segment, frame: FRAME_LOCAL_MAP };
    out.send(s)?;
    Ok(())
}

fn reason_code(r: &Option<SegmentReason>) -> u32 {
    match r {
        None => SEGMENT_REASON_NONE,
        Some(SegmentReason::FewMatches { .. }) => SEGMENT_REASON_FEW_MATCHES,
        Some(SegmentReason::PoseUncertainty { .. }) => SEGMENT_REASON_POSE_UNCERTAINTY,
        Some(SegmentReason::Requested) => SEGMENT_REASON_REQUESTED,
    }
}

/// Sums over the run for summary.json.
#[derive(Default)]
struct RunStats {
    frames: u64,
    nis_sum: f64,
    nis_frames: u64,
    candidates_sum: f64,
    rejected: u64,
    frontend_ms_sum: f64,
}

impl RunStats {
    fn add(&mut self, r: &fastslam::FrameReport, frontend_ms: f64) {
        self.frames += 1;
        if r.mean_nis.is_finite() {
            self.nis_sum += r.mean_nis;
            self.nis_frames += 1;
        }
        self.candidates_sum += r.candidates_per_observation;
        self.rejected += r.rejected as u64;
        self.frontend_ms_sum += frontend_ms;
    }
}

/// The `fastslam` stage.
pub struct FastSlamStage {
    settings: FastSlamSettings,
    st: SlamState,
    body_from_camera: nalgebra::Isometry3<f64>,
    odometry: Input<OdometryInput, MsgHeader>,
    stereo: Input<[StereoObservation], MsgHeader>,
    commands: Input<ControlCommand, MsgHeader>,
    out: Outputs,
    journalled_origins: Option<u32>,
    update_ms: Vec<f64>,
    registration_failures: u64,
    run_stats: RunStats,
    last_landmarks: Instant,
    landmark_every: Option<Duration>,
    out_dir: std::path::PathBuf,
}

impl FastSlamStage {
    /// Takes the odometry, a few stereo frames and the commands. Returns whether more frames wait
    /// in the service's queue.
    fn take_inputs(&mut self, rt: &mut Runtime, inputs_ended: bool) -> Result<bool, StageError> {
        let st = &mut self.st;
        while let Some(s) = self.odometry.receive()? {
            st.push_odometry(s.user_header().stamp_ns, s.payload());
        }
        // Take at most a few frames into the own queue: the rest stay in the service's queue,
        // so a source replaying as fast as possible feels the back-pressure and stays at most a
        // few frames ahead (else it runs ahead by the whole data set and every consumer of the
        // SLAM poses waits for minutes of data time).
        let mut more_waiting = false;
        while inputs_ended || st.frames.len() < MAX_QUEUED_FRAMES {
            let Some(s) = self.stereo.receive()? else { break };
            let h = s.user_header();
            st.frames.push_back(frame_from_wire(h.stamp_ns, h.origin_ns, s.payload(), &self.body_from_camera));
            more_waiting = st.frames.len() >= MAX_QUEUED_FRAMES;
        }
        while let Some(s) = self.commands.receive()? {
            let c = s.payload();
            let target = name_from32(&c.target);
            if (target.is_empty() || target == rt.name()) && c.command == COMMAND_NEW_SEGMENT {
                tracing::info!("new local map requested");
                st.filter.start_new_segment(SegmentReason::Requested);
                let t = st.last_frame_ns.unwrap_or(0) as f64 / 1e9;
                st.segment_origins_s.insert(st.filter.segment(), t);
            }
        }
        Ok(more_waiting)
    }

    /// Journals the new local maps' origins and the last `processed` trajectory samples.
    fn journal(&mut self, rt: &mut Runtime, processed: usize) -> Result<(), StageError> {
        let st = &self.st;
        for (&seg, &t) in st.segment_origins_s.range(self.journalled_origins.map_or(0, |s| s + 1)..) {
            crate::journal::record_origin(rt.state(), seg, t);
            self.journalled_origins = Some(seg);
        }
        for s in &st.trajectory[st.trajectory.len() - processed..] {
            crate::journal::record_sample(rt.state(), s);
        }
        rt.state().flush()?;
        Ok(())
    }

    /// Publishes a processed frame: the pose, the particles, the diagnostics and, when due, the
    /// landmarks; counts a frame without a motion from the front end.
    fn publish_frame(&mut self, p: &crate::Processed, per_frame_ms: f64) -> Result<(), StageError> {
        self.update_ms.push(per_frame_ms);
        let (settings, out) = (&self.settings, &mut self.out);
        let f = &self.st.filter;
        let e = f.estimate();
        let h = header(p.stamp_ns, p.origin_ns);
        out.pose.send_value(
            h,
            PoseEstimate::from_nalgebra(&e.map_from_body, &e.covariance, f.segment(), FRAME_LOCAL_MAP),
        )?;
        let parts: Vec<_> = f.particles().collect();
        let mut s = out
            .particles
            .loan_slice_uninit(parts.len())?
            .write_from_fn(|i| Particle::from_nalgebra(parts[i].0, parts[i].1));
        *s.user_header_mut() =
            ParticleSetHeader { msg: h, segment_id: f.segment(), _reserved: 0, n_eff: p.report.n_eff };
        out.particles.send(s)?;
        let r = &p.report;
        if let Some(reason) = &r.new_segment {
            tracing::info!(segment = f.segment(), "new local map: {reason}");
        }
        if let Some(m) = &p.motion
            && let Err(e) = &m.registration
            && !matches!(e, RegistrationError::FirstFrame)
        {
            // Every failure is counted (summary.json); the log says so for the first ones
            // and then once per 100.
            self.registration_failures += 1;
            let n = self.registration_failures;
            if n <= 10 || n.is_multiple_of(100) {
                tracing::warn!(
                    stamp_ns = p.stamp_ns,
                    failures = n,
                    "stereo front end found no motion ({e}): constant velocity for this frame"
                );
            }
        }
        self.run_stats.add(r, p.frontend_ms);
        out.diagnostics.send_value(
            h,
            SlamDiagnostics {
                segment_id: f.segment(),
                matched: r.matched as u32,
                new_landmarks: r.new as u32,
                ambiguous: r.ambiguous as u32,
                landmarks: r.landmarks as u32,
                new_segment_reason: reason_code(&r.new_segment),
                particles: settings.filter.particles as u32,
                resampled: r.resampled as u32,
                n_eff: r.n_eff,
                update_ms: per_frame_ms,
                motion_source: p.motion_source(settings.motion_model),
                registration_inliers: p
                    .motion
                    .as_ref()
                    .and_then(|m| m.registration.as_ref().ok())
                    .map_or(0, |r| r.inliers as u32),
                rejected: r.rejected as u32,
                _reserved: 0,
                candidates_per_observation: r.candidates_per_observation,
                mean_nis: r.mean_nis,
                frontend_ms: p.frontend_ms,
            },
        )?;
        if self.landmark_every.is_some_and(|every| self.last_landmarks.elapsed() >= every) {
            self.last_landmarks = Instant::now();
            publish_landmarks(&mut out.landmarks, f, p.stamp_ns, p.origin_ns)?;
        }
        Ok(())
    }
}

impl Stage for FastSlamStage {
    type Settings = FastSlamSettings;

    fn open(ctx: &ProcessContext, settings: FastSlamSettings, rt: &mut Runtime) -> Result<Self, StageError> {
        let filter =
            FastSlam::new(settings.filter.clone()).map_err(|p| StageError::Settings(format!("filter: {p:?}")))?;
        let body_from_camera = settings.body_from_camera();
        let odometry = rt.input(ODOMETRY)?;
        let stereo = rt.input_with_buffer(STEREO, settings.stereo_queue)?;
        let commands = rt.input(COMMAND)?;
        let out = Outputs {
            pose: rt.output(SLAM_POSE)?,
            particles: rt.output_slice(SLAM_PARTICLES, settings.filter.particles)?,
            landmarks: rt.output_slice(SLAM_LANDMARKS, 4096)?,
            diagnostics: rt.output(SLAM_DIAGNOSTICS)?,
        };
        let st = SlamState::with_frontend(filter, settings.motion_model, settings.frontend.clone(), body_from_camera);
        let landmark_every =
            (settings.landmarks_rate_hz > 0.0).then(|| Duration::from_secs_f64(1.0 / settings.landmarks_rate_hz));
        tracing::info!(particles = settings.filter.particles, proposal = ?settings.filter.proposal, motion = ?settings.motion_model, "filter ready");
        Ok(Self {
            settings,
            st,
            body_from_camera,
            odometry,
            stereo,
            commands,
            out,
            journalled_origins: None,
            update_ms: vec![],
            registration_failures: 0,
            run_stats: RunStats::default(),
            last_landmarks: Instant::now(),
            landmark_every,
            out_dir: ctx.out_dir.clone(),
        })
    }

    fn end_after(&self) -> EndAfter {
        EndAfter::FirstUpstream
    }

    /// A restarted instance keeps the killed one's trajectory and goes on in a new local map.
    fn restore(&mut self, restart: Restart) -> Result<usize, StageError> {
        let (r, lines) = crate::journal::parse(&restart.journal);
        tracing::info!(
            frames = r.trajectory.len(),
            segment = r.next_segment(),
            "restarted: kept the killed instance's trajectory; its local maps are lost, a new one starts"
        );
        self.st.resume(r);
        // Every origin restored is in the journal already.
        self.journalled_origins = self.st.segment_origins_s.keys().next_back().copied();
        Ok(lines)
    }

    fn step(&mut self, rt: &mut Runtime, _wake: Wake, inputs_ended: bool) -> Result<Step, StageError> {
        let more_waiting = self.take_inputs(rt, inputs_ended)?;
        // One frame per loop iteration: the inputs are drained between frames, so a source
        // waiting on our queues (back-pressure) never waits for more than one frame's work.
        let t0 = Instant::now();
        let processed = self.st.step(inputs_ended, 1);
        // Journal before publishing: a restarted instance resumes from what was journalled.
        self.journal(rt, processed.len())?;
        // Frames in the own queue are not processed yet: lost (and counted) if it is killed now.
        self.stereo.set_held(self.st.frames.len() as u64);
        let busy = !self.st.frames.is_empty() || more_waiting;
        let per_frame =
            if processed.is_empty() { 0.0 } else { t0.elapsed().as_secs_f64() * 1e3 / processed.len() as f64 };
        for p in processed {
            self.publish_frame(&p, per_frame)?;
        }
        Ok(if busy { Step::Busy } else { Step::Idle })
    }

    type Summary = FastSlamPart;

    fn finish(&mut self, _rt: &mut Runtime, ending: Ending) -> Result<Self::Summary, StageError> {
        let st = &self.st;
        match ending {
            Ending::EndOfStream => {
                let stamp = st.last_frame_ns.unwrap_or(0);
                publish_landmarks(&mut self.out.landmarks, &st.filter, stamp, 0)?;
            }
            Ending::Stopped => {
                tracing::info!(frames = st.trajectory.len(), "stopped early: writing the outputs so far")
            }
        }
        summary(st, &self.settings, &self.out_dir, &self.update_ms, &self.run_stats)
    }

    fn end_of_stream(&self) -> (u64, u64) {
        (self.out.pose.sent().saturating_sub(1), self.out.pose.sent())
    }
}

fn summary(
    st: &SlamState,
    settings: &FastSlamSettings,
    out_dir: &std::path::Path,
    update_ms: &[f64],
    stats: &RunStats,
) -> Result<FastSlamPart, StageError> {
    std::fs::create_dir_all(out_dir)?;
    let mut tum = String::new();
    let mut seg = String::from("t_s,segment\n");
    for s in &st.trajectory {
        let v = s.map_from_body.translation.vector;
        let q = convert::quat_to_xyzw(&s.map_from_body.rotation);
        tum.push_str(&format!(
            "{:.9} {:.6} {:.6} {:.6} {:.9} {:.9} {:.9} {:.9}\n",
            s.t_s, v.x, v.y, v.z, q[0], q[1], q[2], q[3]
        ));
        seg.push_str(&format!("{:.9},{}\n", s.t_s, s.segment));
    }
    std::fs::write(out_dir.join("slam_local.tum"), tum)?;
    std::fs::write(out_dir.join("slam_segments.csv"), seg)?;
    let proposal = serde_json::to_value(settings.filter.proposal)?.as_str().unwrap_or_default().to_string();
    let mut part = FastSlamPart {
        slam: SlamSummary {
            particles: settings.filter.particles,
            proposal,
            frames: st.trajectory.len(),
            segments: st.filter.segment() + 1,
            update_ms: Percentiles::of(update_ms),
            rejected_observations: st.rejected_observations,
            rejected_odometry: st.rejected_odometry,
            motion_model: settings.motion_model,
            mean_nis: (stats.nis_frames > 0).then(|| stats.nis_sum / stats.nis_frames as f64),
            candidates_per_observation: stats.candidates_sum / stats.frames.max(1) as f64,
            rejected_track_matches: stats.rejected,
            frontend: None,
            per_segment: None,
        },
        ate_m: None,
        nees: None,
    };
    if let Some(cam) = &st.camera_only {
        let c = cam.stats();
        part.slam.frontend = Some(FrontendSummary {
            frames: c.frames,
            by_track_ids: c.by_track_ids,
            guided: c.guided,
            search: c.search,
            failed: c.failed,
            mean_inliers: c.inliers as f64 / (c.by_track_ids + c.guided + c.search).max(1) as f64,
            mean_ms: stats.frontend_ms_sum / stats.frames.max(1) as f64,
            bridged_tracks: c.bridged,
        });
        if c.failed > 0 {
            tracing::warn!(
                failed = c.failed,
                frames = c.frames,
                "the stereo front end found no motion for {} of {} frames (constant velocity instead)",
                c.failed,
                c.frames
            );
        }
    }
    let gt_path = out_dir.join(&settings.ground_truth);
    match fastslam::eval::read_tum(&gt_path) {
        Ok(truth) => {
            let scores = fastslam::eval::evaluate(&st.trajectory, &truth, &st.segment_origins_s);
            let ate = fastslam::eval::overall_ate(&scores);
            let n: usize = scores.iter().filter(|s| s.nees.is_finite()).map(|s| s.samples).sum();
            let nees = scores.iter().filter(|s| s.nees.is_finite()).map(|s| s.nees * s.samples as f64).sum::<f64>()
                / n.max(1) as f64;
            let nees_position = fastslam::eval::weighted_mean(&scores, |s| s.nees_position);
            let in95 = fastslam::eval::weighted_mean(&scores, |s| s.nees_position_in_95);
            tracing::info!(
                "ATE {ate:.3} m over {} segment(s) (aligned per segment), mean NEES {nees:.2}, position NEES {nees_position:.2} ({:.0}% of poses in the 95% interval of χ²₃)",
                scores.len(),
                in95 * 100.0
            );
            part.ate_m = Some(SlamAte { slam: finite(ate) });
            part.nees = Some(SlamNees {
                slam: finite(nees),
                slam_position: finite(nees_position),
                slam_position_in_95: finite(in95),
            });
            part.slam.per_segment = Some(scores.iter().map(SegmentSummary::from).collect());
        }
        Err(e) => tracing::info!("no accuracy evaluation: {e}"),
    }
    Ok(part)
}
