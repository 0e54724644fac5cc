//! `grid_slam` as a [`Stage`]: ports around the [`ScanQueue`] and the filter. It ends after the
//! first upstream end of stream (its inputs come from one source), once no scan waits.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use grid_slam::backend::{BackEnd, BackEndResult};
use grid_slam::densify::densify;
use grid_slam::export::{Occupancy, write_tum2};
use grid_slam::relations::{read_relations, score};
use grid_slam::{GridSlam, GridSlamError, Pose2, ScanGeometry};
use nalgebra::{UnitQuaternion, Vector3};
use pipeline_runtime::stage::{EndAfter, Ending, Stage, Step};
use pipeline_runtime::{Input, Output, ProcessContext, Restart, Runtime, StageError, Wake};
use shared_types::services::{
    GRID_SLAM_GRID, GRID_SLAM_PARTICLES, GRID_SLAM_POSE, GRID_SLAM_POSE3D, LASER, PLANAR_ODOMETRY,
};
use shared_types::*;

use crate::summary::{BackEndSummary, GridFiles, GridMemory, GridSlamAte, GridSlamPart, GridSlamRun, GridSlamSummary};
use crate::{BackEndKind, GridSlamSettings, PendingScan, ScanQueue};

/// `PlanarPose::flags` bit: the filter was updated at this scan.
pub const POSE_UPDATED: u32 = 1;
/// `PlanarPose::flags` bit: the particles were resampled at this scan.
pub const POSE_RESAMPLED: u32 = 2;

/// The restart snapshot's key.
pub const SNAPSHOT: &str = "grid_slam.bin";

/// The `grid_slam` stage.
pub struct GridSlamStage {
    settings: GridSlamSettings,
    laser: Input<[LaserRange], LaserScanHeader>,
    odometry: Input<PlanarOdometry, MsgHeader>,
    pose: Output<PlanarPose, MsgHeader>,
    pose3d: Output<PoseEstimate, MsgHeader>,
    particles: Output<[Particle], ParticleSetHeader>,
    grid: Output<[OccupancyCell], OccupancyGridHeader>,
    queue: ScanQueue,
    /// Every odometry sample accepted, (stamp s, pose), with `trajectory_between_scans`.
    odometry_track: Vec<(f64, Pose2)>,
    geometry: Option<ScanGeometry>,
    filter: Option<GridSlam>,
    /// The pose-graph back end's nodes (`back_end = "pose_graph"`).
    back_end: Option<BackEnd>,
    /// Its result, once run at the end.
    closed: Option<BackEndResult>,
    /// Seconds the back end took.
    back_end_s: f64,
    /// Why it failed, if it did (the filter's own outputs are written then).
    back_end_error: Option<String>,
    /// Scans the filter refused, by kind.
    refused: BTreeMap<&'static str, u64>,
    last_grid_ns: Option<u64>,
    last_snapshot_ns: Option<u64>,
    last_stamp_ns: u64,
    out_dir: PathBuf,
    config_dir: PathBuf,
    started: Instant,
}

fn s_of(ns: u64) -> f64 {
    ns as f64 * 1e-9
}

/// The scan geometry a header states, or why it is unusable.
fn geometry_of(h: &LaserScanHeader) -> Result<ScanGeometry, &'static str> {
    let g = ScanGeometry {
        angle_min_rad: h.angle_min_rad,
        angle_increment_rad: h.angle_increment_rad,
        beams: h.beams as usize,
        range_min_m: h.range_min_m,
        range_max_m: h.range_max_m,
        body_from_laser: Pose2 {
            x_m: h.body_from_laser_xy_m[0],
            y_m: h.body_from_laser_xy_m[1],
            theta_rad: h.body_from_laser_yaw_rad,
        },
    };
    let finite =
        [g.body_from_laser.x_m, g.body_from_laser.y_m, g.body_from_laser.theta_rad].iter().all(|v| v.is_finite());
    if !pipeline_runtime::Validate::issues(&g).is_empty() || !finite {
        return Err("laser_geometry_invalid");
    }
    Ok(g)
}

impl GridSlamStage {
    fn count(map: &mut BTreeMap<&'static str, u64>, kind: &'static str, what: impl FnOnce() -> String) {
        let n = map.entry(kind).or_default();
        if *n == 0 {
            tracing::warn!("{} (counted as {kind}; further ones are counted, not logged)", what());
        }
        *n += 1;
    }

    fn receive(&mut self) -> Result<(), StageError> {
        // The scans received up to now were published before the odometry received next.
        self.queue.settle();
        while let Some(s) = self.odometry.receive()? {
            let (h, o) = (s.user_header(), s.payload());
            let pose = Pose2 { x_m: o.position_m[0], y_m: o.position_m[1], theta_rad: o.yaw_rad };
            let before = self.queue.rejected.clone();
            if !self.queue.push_odometry(h.stamp_ns, pose) {
                warn_new(&before, &self.queue.rejected);
            } else if self.settings.trajectory_between_scans {
                self.odometry_track.push((s_of(h.stamp_ns), pose));
            }
        }
        while let Some(s) = self.laser.receive()? {
            let h = *s.user_header();
            let ranges = s.payload();
            if h.beams as usize != ranges.len() {
                Self::count(&mut self.refused, "scans_beam_count_mismatch", || {
                    format!(
                        "scan at {:.3} s: header says {} beams, the slice has {}",
                        s_of(h.msg.stamp_ns),
                        h.beams,
                        ranges.len()
                    )
                });
                continue;
            }
            let g = match geometry_of(&h) {
                Ok(g) => g,
                Err(kind) => {
                    Self::count(&mut self.refused, kind, || {
                        format!("scan at {:.3} s: unusable laser geometry {h:?}", s_of(h.msg.stamp_ns))
                    });
                    continue;
                }
            };
            match &self.geometry {
                None => {
                    tracing::info!(
                        beams = g.beams,
                        fov_deg = (g.angle_increment_rad * (g.beams - 1) as f64).to_degrees(),
                        range_max_m = g.range_max_m,
                        "laser geometry from the first scan"
                    );
                    self.geometry = Some(g);
                }
                Some(first) if *first != g => {
                    Self::count(&mut self.refused, "scans_geometry_changed", || {
                        format!(
                            "scan at {:.3} s: the laser geometry differs from the first scan's: {g:?}",
                            s_of(h.msg.stamp_ns)
                        )
                    });
                    continue;
                }
                Some(_) => {}
            }
            let before = self.queue.rejected.clone();
            let scan = PendingScan {
                stamp_ns: h.msg.stamp_ns,
                origin_ns: h.msg.origin_ns,
                ranges: ranges.iter().map(|r| r.range_m).collect(),
            };
            if !self.queue.push_scan(scan) {
                warn_new(&before, &self.queue.rejected);
            }
        }
        Ok(())
    }

    fn process(&mut self, scan: PendingScan, odom: Pose2) -> Result<(), StageError> {
        let Some(geom) = self.geometry else { return Ok(()) };
        if self.filter.is_none() {
            self.filter = Some(GridSlam::new(self.settings.filter.clone(), geom).map_err(StageError::stage)?);
        }
        let f = self.filter.as_mut().expect("created above");
        let t_s = s_of(scan.stamp_ns);
        let out = match f.process(t_s, odom, &scan.ranges) {
            Ok(o) => o,
            Err(e) => {
                let kind = match e {
                    GridSlamError::BeamCount { .. } => "scans_wrong_beam_count",
                    GridSlamError::Stamp { .. } => "scans_stamp_not_increasing",
                    GridSlamError::Odometry { .. } => "scans_odometry_not_finite",
                    _ => "scans_filter_error",
                };
                Self::count(&mut self.refused, kind, || format!("scan at {t_s:.3} s refused: {e}"));
                return Ok(());
            }
        };
        if out.updated
            && let Some(b) = self.back_end.as_mut()
        {
            b.add_node(out.update, &scan.ranges);
        }
        self.last_stamp_ns = scan.stamp_ns;
        let header = MsgHeader { stamp_ns: scan.stamp_ns, origin_ns: scan.origin_ns, ..Default::default() };
        let cov = f.covariance();
        let flags = if out.updated { POSE_UPDATED } else { 0 } | if out.resampled { POSE_RESAMPLED } else { 0 };
        let p = out.pose;
        self.pose.send_value(
            header,
            PlanarPose {
                position_m: [p.x_m, p.y_m],
                yaw_rad: p.theta_rad,
                covariance: cov,
                n_eff: out.n_eff,
                updates: f.stats().updates as u32,
                flags,
            },
        )?;
        // Lifted to 3-D: z 0, roll and pitch 0; (x, y, yaw) → indices (0, 1, 5) of the 6×6.
        let mut c6 = [0.0; 36];
        let idx = [0usize, 1, 5];
        for r in 0..3 {
            for c in 0..3 {
                c6[idx[r] * 6 + idx[c]] = cov[r * 3 + c];
            }
        }
        let q = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), p.theta_rad);
        self.pose3d.send_value(
            header,
            PoseEstimate {
                position_m: [p.x_m, p.y_m, 0.0],
                orientation_xyzw: [q.i, q.j, q.k, q.w],
                covariance: c6,
                segment_id: 0,
                frame: FRAME_WORLD,
            },
        )?;
        if out.updated && self.settings.publish_particles {
            let ps = f.particles();
            let mut s = self.particles.loan_slice_uninit(ps.len())?.write_from_fn(|i| {
                let (pp, w) = ps[i];
                let q = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), pp.theta_rad);
                Particle {
                    position_m: [pp.x_m, pp.y_m, 0.0],
                    orientation_xyzw: [q.i, q.j, q.k, q.w],
                    log_weight: w.max(f64::MIN_POSITIVE).ln(),
                }
            });
            *s.user_header_mut() = ParticleSetHeader { msg: header, segment_id: 0, _reserved: 0, n_eff: out.n_eff };
            self.particles.send(s)?;
        }
        let every_ns = (self.settings.grid_every_s * 1e9) as u64;
        if every_ns > 0 && self.last_grid_ns.is_none_or(|t| scan.stamp_ns.saturating_sub(t) >= every_ns) {
            self.last_grid_ns = Some(scan.stamp_ns);
            self.publish_grid(header)?;
        }
        Ok(())
    }

    /// Runs the back end over the filter's final path (once).
    fn close_loops(&mut self, rt: &mut Runtime) {
        let (Some(b), Some(f)) = (&self.back_end, &self.filter) else { return };
        if self.closed.is_some() || self.back_end_error.is_some() {
            return;
        }
        // Seconds of bounded work, not a hang: the heartbeat goes on meanwhile.
        let _alive = rt.hold_heartbeat();
        tracing::info!(nodes = b.len(), "pose graph: searching loop closures over the filter's final path");
        let t0 = Instant::now();
        match b.run(f) {
            Ok(r) => {
                let rep = &r.report;
                tracing::info!(
                    nodes = rep.nodes,
                    submaps = rep.submaps,
                    searched = rep.searched,
                    loop_constraints = rep.loop_constraints,
                    rejected = rep.rejected,
                    mean_correction_m = rep.mean_correction_m,
                    max_correction_m = rep.max_correction_m,
                    "pose graph optimised in {:.1} s: the grid and grid_slam.tum are written from its poses",
                    t0.elapsed().as_secs_f64()
                );
                self.closed = Some(r);
            }
            Err(e) => {
                tracing::warn!("pose graph failed, writing the filter's own path and map: {e}");
                self.back_end_error = Some(e.to_string());
            }
        }
        self.back_end_s = t0.elapsed().as_secs_f64();
    }

    /// The final grid: the back end's when it ran, else the best particle's.
    fn final_grid(&self) -> Option<&grid_slam::grid::Grid> {
        self.closed.as_ref().map(|r| &r.grid).or_else(|| self.filter.as_ref().and_then(|f| f.best_grid()))
    }

    fn publish_grid(&mut self, header: MsgHeader) -> Result<(), StageError> {
        let Some(g) = self.final_grid() else { return Ok(()) };
        let occ = Occupancy::from_grid(g, self.settings.grid_margin_cells);
        if occ.data.is_empty() {
            return Ok(());
        }
        let mut s =
            self.grid.loan_slice_uninit(occ.data.len())?.write_from_fn(|i| OccupancyCell { value: occ.data[i] });
        *s.user_header_mut() = OccupancyGridHeader {
            msg: header,
            resolution_m: occ.resolution_m,
            origin_m: [occ.origin_m.0, occ.origin_m.1],
            width: occ.width as u32,
            height: occ.height as u32,
        };
        self.grid.send(s)?;
        Ok(())
    }

    /// The end of the run: `grid_slam.tum`, the map_server grid and its picture, the scores
    /// against the relations and the ground truth, and the summary part.
    fn summary(&self) -> Result<GridSlamPart, StageError> {
        std::fs::create_dir_all(&self.out_dir)?;
        let mut rejected: BTreeMap<&str, u64> = self.queue.rejected.clone();
        rejected.extend(self.refused.iter().map(|(k, v)| (*k, *v)));
        let n_rejected: u64 = rejected.values().sum();
        if n_rejected > 0 {
            tracing::warn!(?rejected, "inputs rejected (counted in summary.json grid_slam.rejected)");
        }
        let rejected = rejected.iter().map(|(k, n)| (k.to_string(), *n)).collect();
        let Some(f) = &self.filter else {
            tracing::warn!("no scan was processed: no map, no trajectory");
            return Ok(GridSlamPart { grid_slam: GridSlamSummary { scans: 0, rejected, run: None }, ate_m: None });
        };
        let front_traj = densify(&f.trajectory(), &self.odometry_track);
        let traj = match &self.closed {
            Some(r) => densify(&f.trajectory_with(&r.nodes), &self.odometry_track),
            None => front_traj.clone(),
        };
        if self.settings.trajectory_between_scans {
            tracing::info!(
                "grid_slam.tum: {} poses, {} of them between scans (shaped by the odometry)",
                traj.len(),
                traj.len() - f.trajectory().len()
            );
        }
        write_tum2(&self.out_dir.join("grid_slam.tum"), &traj).map_err(StageError::stage)?;
        let mut run = self.run_summary(f, self.write_grid(&traj)?);
        self.score_relations(&traj, &front_traj, &mut run);
        let ate_m = self.score_against_truth(&traj);
        if let Some(n) = f.n_eff_summary() {
            tracing::info!(
                mean = n.mean_share,
                p10 = n.p10_share,
                distinct_ancestors = n.distinct_ancestors,
                "N_eff / N over the {} updates; particles of the first set with descendants at the end",
                n.updates
            );
        }
        let st = f.stats();
        tracing::info!(
            scans = st.scans,
            updates = st.updates,
            resamples = st.resamples,
            "grid SLAM done: grid.pgm, grid.yaml, grid.png, grid_slam.tum in {}",
            self.out_dir.display()
        );
        Ok(GridSlamPart { grid_slam: GridSlamSummary { scans: st.scans, rejected, run: Some(run) }, ate_m })
    }

    /// Writes the final grid (`grid.pgm` + `grid.yaml`, and `grid.png` with the path `traj`).
    fn write_grid(&self, traj: &[(f64, Pose2)]) -> Result<Option<GridFiles>, StageError> {
        let Some(g) = self.final_grid() else { return Ok(None) };
        let occ = Occupancy::from_grid(g, self.settings.grid_margin_cells);
        occ.write_map_server(&self.out_dir, "grid").map_err(StageError::stage)?;
        let path: Vec<Pose2> = traj.iter().map(|p| p.1).collect();
        occ.write_png(&self.out_dir.join("grid.png"), &path).map_err(StageError::stage)?;
        Ok(Some(GridFiles {
            pgm: "grid.pgm".into(),
            yaml: "grid.yaml".into(),
            png: "grid.png".into(),
            width: occ.width,
            height: occ.height,
            resolution_m: occ.resolution_m,
            origin_m: [occ.origin_m.0, occ.origin_m.1],
        }))
    }

    /// The filter's and the back end's counts (no scores yet).
    fn run_summary(&self, f: &GridSlam, grid: Option<GridFiles>) -> GridSlamRun {
        let st = f.stats();
        let mem = f.peak_memory();
        let one_map = f.memory().best_bytes;
        GridSlamRun {
            updates: st.updates,
            resamples: st.resamples,
            n_eff: f.n_eff_summary(),
            particles: f.config().particles,
            resolution_m: f.config().resolution_m,
            poses_published: self.pose.sent(),
            grids_published: self.grid.sent(),
            particle_sets_published: self.particles.sent(),
            invalid_beams: st.invalid_beams,
            tracking_failures: st.tracking_failures,
            proposal_fallbacks: st.proposal_fallbacks,
            update_matches: st.matches,
            memory: GridMemory {
                peak_bytes: mem.map(|m| m.bytes),
                one_map_bytes: one_map,
                tiles_shared: st.shared_tiles,
                peak_over_one_map: mem.map(|m| m.bytes as f64 / one_map.max(1) as f64),
            },
            grid,
            trajectory: "grid_slam.tum".into(),
            back_end: BackEndSummary {
                kind: self.settings.back_end,
                report: self.closed.as_ref().map(|r| r.report.clone()),
                wall_s: self.back_end_s,
                error: self.back_end_error.clone(),
                scans_bytes: self.back_end.as_ref().map(|b| b.bytes()),
            },
            wall_s: self.started.elapsed().as_secs_f64(),
            relations: None,
            relations_front_end: None,
        }
    }

    /// Scores the final trajectory (and the filter's own, when the back end moved it) against the
    /// configured relations file (Kümmerle et al. 2009), if any.
    fn score_relations(&self, traj: &[(f64, Pose2)], front_traj: &[(f64, Pose2)], run: &mut GridSlamRun) {
        if self.settings.relations.as_os_str().is_empty() {
            return;
        }
        let path = if self.settings.relations.is_absolute() {
            self.settings.relations.clone()
        } else {
            self.config_dir.join(&self.settings.relations)
        };
        let rel = match read_relations(&path) {
            Ok(rel) => rel,
            Err(e) => {
                tracing::warn!("relations not scored: {e}");
                return;
            }
        };
        let s = score(traj, &rel, self.settings.relations_offset_s, 2.0);
        tracing::info!(
            "relations ({}): {} scored, {} not covered: {:.4} ± {:.4} m, {:.3} ± {:.3} deg; {} over {:.0} s: \
             {:.4} m; {:.1} % over {} m",
            path.display(),
            s.scored,
            s.uncovered,
            s.trans_mean_m,
            s.trans_std_m,
            s.rot_mean_deg,
            s.rot_std_deg,
            s.long_scored,
            grid_slam::relations::LONG_SPAN_S,
            s.long_trans_mean_m,
            100.0 * s.over_far_share,
            grid_slam::relations::FAR_OFF_M
        );
        run.relations = Some(s);
        if self.closed.is_some() {
            let fs = score(front_traj, &rel, self.settings.relations_offset_s, 2.0);
            tracing::info!(
                "relations of the filter alone (before the pose graph): {:.4} ± {:.4} m, {:.3} deg; over {:.0} s: {:.4} m; {:.1} % over {} m",
                fs.trans_mean_m,
                fs.trans_std_m,
                fs.rot_mean_deg,
                grid_slam::relations::LONG_SPAN_S,
                fs.long_trans_mean_m,
                100.0 * fs.over_far_share,
                grid_slam::relations::FAR_OFF_M
            );
            run.relations_front_end = Some(fs);
        }
    }

    /// The planar ATE against the source's ground truth, when it wrote one.
    fn score_against_truth(&self, traj: &[(f64, Pose2)]) -> Option<GridSlamAte> {
        let gt_path = self.out_dir.join(&self.settings.ground_truth);
        match geometry::tum::read_tum(&gt_path) {
            Ok(truth) if !truth.is_empty() => {
                let truth_p: Vec<(f64, Vector3<f64>)> = truth.iter().map(|(t, p)| (*t, p.translation.vector)).collect();
                let est: Vec<(f64, Vector3<f64>)> =
                    traj.iter().map(|(t, p)| (*t, Vector3::new(p.x_m, p.y_m, 0.0))).collect();
                let ate = geometry::trajectory::ate_nearest(&est, &truth_p, true);
                tracing::info!("ATE (2-D, nearest stamp, against {}): grid SLAM {ate:.3} m", gt_path.display());
                Some(GridSlamAte { grid_slam: pipeline_runtime::summary::finite(ate) })
            }
            Ok(_) => {
                tracing::info!("no accuracy evaluation: {} is empty", gt_path.display());
                None
            }
            Err(e) => {
                tracing::info!("no accuracy evaluation: {e}");
                None
            }
        }
    }
}

/// Warns the first time a kind of rejection appears.
fn warn_new(before: &BTreeMap<&'static str, u64>, after: &BTreeMap<&'static str, u64>) {
    for (k, n) in after {
        if before.get(k).copied().unwrap_or(0) == 0 && *n > 0 {
            tracing::warn!("input rejected: {k} (further ones are counted, not logged)");
        }
    }
}

impl Stage for GridSlamStage {
    type Settings = GridSlamSettings;

    fn open(ctx: &ProcessContext, settings: GridSlamSettings, rt: &mut Runtime) -> Result<Self, StageError> {
        let laser = rt.input(LASER)?;
        let odometry = rt.input(PLANAR_ODOMETRY)?;
        let pose = rt.output(GRID_SLAM_POSE)?;
        let pose3d = rt.output(GRID_SLAM_POSE3D)?;
        let particles = rt.output_slice(GRID_SLAM_PARTICLES, settings.filter.particles.max(1))?;
        let grid = rt.output_slice(GRID_SLAM_GRID, 1024 * 1024)?;
        let back_end = match settings.back_end {
            BackEndKind::PoseGraph => Some(BackEnd::new(settings.pose_graph).map_err(StageError::stage)?),
            BackEndKind::None => None,
        };
        tracing::info!(
            particles = settings.filter.particles,
            resolution_m = settings.filter.resolution_m,
            back_end = ?settings.back_end,
            "grid SLAM ready"
        );
        Ok(Self {
            settings,
            laser,
            odometry,
            pose,
            pose3d,
            particles,
            grid,
            queue: ScanQueue::default(),
            odometry_track: Vec::new(),
            geometry: None,
            filter: None,
            back_end,
            closed: None,
            back_end_s: 0.0,
            back_end_error: None,
            refused: BTreeMap::new(),
            last_grid_ns: None,
            last_snapshot_ns: None,
            last_stamp_ns: 0,
            out_dir: ctx.out_dir.clone(),
            config_dir: ctx.config.source.parent().unwrap_or(std::path::Path::new(".")).to_path_buf(),
            started: Instant::now(),
        })
    }

    fn end_after(&self) -> EndAfter {
        EndAfter::FirstUpstream
    }

    fn tick(&self) -> Option<Duration> {
        Some(Duration::from_millis(200))
    }

    fn step(&mut self, rt: &mut Runtime, _wake: Wake, inputs_ended: bool) -> Result<Step, StageError> {
        self.receive()?;
        let wait_ns = (self.settings.odometry_wait_s * 1e9) as u64;
        let batch_end = Instant::now() + Duration::from_millis(50);
        let mut busy = false;
        while let Some((scan, odom)) = self.queue.pop(wait_ns, inputs_ended) {
            self.process(scan, odom)?;
            if Instant::now() > batch_end {
                busy = true;
                break;
            }
        }
        let every_ns = (self.settings.snapshot_every_s * 1e9) as u64;
        if every_ns > 0
            && let Some(f) = &self.filter
            && self.last_snapshot_ns.is_none_or(|t| self.last_stamp_ns.saturating_sub(t) >= every_ns)
        {
            self.last_snapshot_ns = Some(self.last_stamp_ns);
            rt.state().snapshot(SNAPSHOT, &f.snapshot())?;
        }
        // Busy: let the loop send heartbeats, and come back at once.
        Ok(if busy {
            Step::Busy
        } else if self.queue.pending() == 0 {
            Step::Idle
        } else {
            Step::Pending
        })
    }

    /// A restarted instance goes on from the killed one's last snapshot: the best particle's map
    /// and pose (copied to every particle) and the trajectory up to it.
    fn restore(&mut self, restart: Restart) -> Result<usize, StageError> {
        if let Some(bytes) = restart.read_snapshot(SNAPSHOT)?
            && !bytes.is_empty()
        {
            let f = GridSlam::restore(self.settings.filter.clone(), &bytes).map_err(StageError::stage)?;
            tracing::info!(
                scans = f.stats().scans,
                poses = f.trajectory().len(),
                "restarted: going on from the killed instance's last snapshot (its map and trajectory)"
            );
            self.geometry = Some(*f.geometry());
            self.filter = Some(f);
        }
        Ok(0)
    }

    type Summary = GridSlamPart;

    fn finish(&mut self, rt: &mut Runtime, ending: Ending) -> Result<Self::Summary, StageError> {
        if ending == Ending::Stopped {
            tracing::info!(poses = self.pose.sent(), "stopped early: writing the outputs so far");
        } else if self.filter.is_some() {
            self.close_loops(rt);
            // The last grid, so a viewer has the final map.
            let h = MsgHeader { stamp_ns: self.last_stamp_ns, ..Default::default() };
            self.publish_grid(h)?;
        }
        self.summary()
    }

    fn end_of_stream(&self) -> (u64, u64) {
        (self.pose.sent().saturating_sub(1), self.pose.sent())
    }
}
