//! The buoy EKF as a [`Stage`]: its ports and journal around [`BuoyState`]. It ends after the
//! first upstream end of stream (its inputs come from one source), once no ranges wait.

use pipeline_runtime::StageError;
use std::time::{Duration, Instant};

use buoy::Mode;
use nalgebra::Vector3;
use pipeline_runtime::stage::{EndAfter, Ending, Stage, Step};
use pipeline_runtime::{Input, Output, ProcessContext, Restart, Runtime, Wake};
use shared_types::services::{BUOY_FIX, BUOY_RANGES, DEPTH, ODOMETRY};
use shared_types::*;

use crate::summary::{BuoyAte, BuoyEkfPart, BuoyEkfSummary, BuoyNeesPart, PerBuoy, RangeBias, RangeNis, RejectedShare};
use crate::{BuoyEkfSettings, BuoyState, fix_pose};
use geometry::trajectory::{ate_nearest, dead_reckoning, position_nees};
use pipeline_runtime::summary::{PositionNees, finite};

/// The `buoy_ekf` stage.
pub struct BuoyEkfStage {
    settings: BuoyEkfSettings,
    st: BuoyState,
    odometry: Input<OdometryInput, MsgHeader>,
    ranges: Input<[BuoyRange], MsgHeader>,
    depth: Input<DepthReading, MsgHeader>,
    fixes: Output<BuoyFix, MsgHeader>,
    was_initialised: bool,
    out_dir: std::path::PathBuf,
}

impl Stage for BuoyEkfStage {
    type Settings = BuoyEkfSettings;

    fn open(ctx: &ProcessContext, settings: BuoyEkfSettings, rt: &mut Runtime) -> Result<Self, StageError> {
        let odometry = rt.input(ODOMETRY)?;
        let ranges = rt.input(BUOY_RANGES)?;
        let depth = rt.input(DEPTH)?;
        let fixes = rt.output(BUOY_FIX)?;
        let st = BuoyState::new(settings.clone());
        tracing::info!(buoys = settings.ekf.buoys.len(), mode = ?settings.ekf.mode, odometry = settings.use_odometry, "buoy EKF ready");
        Ok(Self { settings, st, odometry, ranges, depth, fixes, was_initialised: false, out_dir: ctx.out_dir.clone() })
    }

    fn end_after(&self) -> EndAfter {
        EndAfter::FirstUpstream
    }

    fn tick(&self) -> Option<Duration> {
        Some(Duration::from_millis(100))
    }

    /// A restarted instance replays the inputs the killed one's filter took: it goes on from the
    /// killed one's state (nothing is published during the replay).
    fn restore(&mut self, restart: Restart) -> Result<usize, StageError> {
        let (inputs, lines) = crate::journal::parse(&restart.journal);
        let n = inputs.len();
        let fixes = self.st.replay(inputs).len();
        self.was_initialised = self.st.ekf().is_some_and(|e| e.is_initialised());
        tracing::info!(
            inputs = n,
            fixes,
            initialised = self.was_initialised,
            "restarted: replayed the inputs the killed instance's filter took; it goes on from there"
        );
        Ok(lines)
    }

    fn step(&mut self, rt: &mut Runtime, _wake: Wake, inputs_ended: bool) -> Result<Step, StageError> {
        let st = &mut self.st;
        let now = Instant::now();
        while let Some(s) = self.odometry.receive()? {
            st.push_odometry(s.user_header().stamp_ns, s.payload());
        }
        while let Some(s) = self.ranges.receive()? {
            let h = s.user_header();
            st.push_ranges(h.stamp_ns, h.origin_ns, s.payload(), now);
        }
        while let Some(s) = self.depth.receive()? {
            st.push_depth(s.user_header().stamp_ns, s.payload());
        }
        let out = st.step(inputs_ended, now);
        // Journal before publishing: a restarted instance resumes from what was journalled.
        crate::journal::record(rt.state(), &st.take_applied());
        rt.state().flush()?;
        for f in out {
            let e = &f.estimate;
            self.fixes.send_value(
                MsgHeader { stamp_ns: f.stamp_ns, origin_ns: f.origin_ns, ..Default::default() },
                BuoyFix {
                    position_m: e.position_m.into(),
                    covariance_m2: convert::mat3_to_row_major(&e.covariance_m2),
                    velocity_mps: e.velocity_mps.into(),
                    ranges_used: f.used,
                    ranges_rejected: f.rejected,
                    prev_fix_stamp_ns: f.cross_prev.map_or(0, |(t, _)| t),
                    cross_covariance_prev_m2: f.cross_prev.map_or([0.0; 9], |(_, c)| convert::mat3_to_row_major(&c)),
                },
            )?;
        }
        if !self.was_initialised && st.ekf().is_some_and(|e| e.is_initialised()) {
            self.was_initialised = true;
            if let Some(Ok(e)) = st.ekf().map(|e| e.estimate()) {
                tracing::info!(position_m = ?e.position_m.as_slice(), "initialised");
            }
        }
        if let Some(deadline) = st.next_deadline() {
            rt.wake_at(deadline);
        }
        // Inputs waiting to be applied in stamp order: lost (and counted) if it is killed now.
        let (odometry, ranges, depth) = st.held();
        self.odometry.set_held(odometry as u64);
        self.ranges.set_held(ranges as u64);
        self.depth.set_held(depth as u64);
        Ok(if st.pending() == 0 { Step::Idle } else { Step::Pending })
    }

    type Summary = BuoyEkfPart;

    fn finish(&mut self, _rt: &mut Runtime, ending: Ending) -> Result<Self::Summary, StageError> {
        if ending == Ending::Stopped {
            tracing::info!(fixes = self.fixes.sent(), "stopped early: writing the outputs so far");
        }
        summary(&self.st, &self.settings, &self.out_dir, self.fixes.sent())
    }

    fn end_of_stream(&self) -> (u64, u64) {
        (self.fixes.sent().saturating_sub(1), self.fixes.sent())
    }
}

fn summary(
    st: &BuoyState,
    settings: &BuoyEkfSettings,
    out_dir: &std::path::Path,
    fixes_sent: u64,
) -> Result<BuoyEkfPart, StageError> {
    std::fs::create_dir_all(out_dir)?;
    if !st.ekf().is_some_and(|e| e.is_initialised()) {
        tracing::warn!(
            ranges_waiting = st.waiting,
            reason = st.waiting_reason.as_deref().unwrap_or("no ranges came"),
            "the buoy EKF never initialised: no fix was published (settings `ekf.init`, `ekf.buoys`)"
        );
    }
    let planar = settings.ekf.mode == Mode::Planar;
    let poses: Vec<_> = st.trajectory.iter().map(|s| (s.t_s, fix_pose(&s.position_m, s.heading_rad))).collect();
    geometry::tum::write_tum(&out_dir.join("buoy_ekf.tum"), poses.iter().map(|(t, p)| (*t, p)))?;
    let counters = st.ekf().map(|e| e.counters().clone()).unwrap_or_default();
    let estimate = st.ekf().filter(|e| e.is_initialised()).and_then(|e| e.estimate().ok());
    let ekf = st.ekf();
    let mut part = BuoyEkfPart {
        buoy_ekf: BuoyEkfSummary {
            fixes: fixes_sent,
            trajectory_samples: st.trajectory.len(),
            ranges_accepted: counters.accepted,
            range_nis: range_nis(st.range_nis),
            ranges_rejected: counters.rejected,
            recoveries: counters.recoveries,
            reinitialisations: counters.reinitialisations,
            outlier_branch_switches: counters.outlier_branch_switches,
            lost_checks_without_fix: counters.lost_checks_without_fix,
            start_checks: counters.start_checks,
            start_corrections: counters.start_corrections,
            bias_resets: counters.bias_resets,
            calibration_held: counters.calibration_held,
            calibration_unobservable: counters.calibration_unobservable,
            rejected_share_at_end: ekf
                .and_then(|e| e.recent_rejected_share())
                .map(|(share, of_last_ranges)| RejectedShare { share, of_last_ranges }),
            depth_rejected: counters.depth_rejected,
            ranges_waiting_for_initialisation: st.waiting,
            initialised: ekf.is_some_and(|e| e.is_initialised()),
            last_waiting_reason: st.waiting_reason.clone(),
            per_buoy: counters
                .per_buoy
                .iter()
                .map(|b| PerBuoy {
                    id: b.id,
                    accepted: b.accepted,
                    rejected: b.rejected,
                    rejected_share: b.rejected as f64 / (b.accepted + b.rejected).max(1) as f64,
                })
                .collect(),
            range_biases_m: estimate.as_ref().map(|e| {
                e.biases
                    .iter()
                    .map(|b| RangeBias { buoy_id: b.buoy_id, bias_m: b.bias_m, sigma_m: b.sigma_m })
                    .collect()
            }),
            range_scale: estimate.as_ref().and_then(|e| e.range_scale).map(|s| s.0),
            invalid_inputs: st.invalid.clone(),
            filter_errors: st.filter_errors.clone(),
        },
        ate_m: None,
        nees: None,
    };
    let gt_path = out_dir.join(&settings.ground_truth);
    match geometry::tum::read_tum(&gt_path) {
        Ok(truth) if !truth.is_empty() => {
            let truth_p: Vec<(f64, Vector3<f64>)> = truth.iter().map(|(t, p)| (*t, p.translation.vector)).collect();
            let est: Vec<(f64, Vector3<f64>)> = st.trajectory.iter().map(|s| (s.t_s, s.position_m)).collect();
            let ate = ate_nearest(&est, &truth_p, planar);
            // The covariance's consistency: the truth interpolated to each estimate's stamp
            // between rows at most 1 s apart on either side.
            let with_cov: Vec<_> = st.trajectory.iter().map(|s| (s.t_s, s.position_m, s.covariance_m2)).collect();
            if let Some(n) = position_nees(&with_cov, &truth_p, planar, 1.0) {
                let nees = PositionNees::new(n.mean, n.dof, n.samples, n.per_axis, n.skipped, n.interval_95);
                tracing::info!(
                    "position NEES {:.2} over {} estimates ({} degrees of freedom; per axis x, y, z {:.2}, {:.2}, {:.2}; consistent within [{:.2}, {:.2}] at 95 %: {})",
                    n.mean,
                    n.samples,
                    n.dof,
                    n.per_axis[0],
                    n.per_axis[1],
                    n.per_axis[2],
                    n.interval_95.0,
                    n.interval_95.1,
                    nees.verdict()
                );
                part.nees = Some(BuoyNeesPart { buoy_ekf: nees });
            }
            let mut ates = BuoyAte { buoy_ekf: finite(ate), dead_reckoning: None };
            if let Some((t0, u0)) = st.inputs.first() {
                // Dead reckoning from the ground-truth pose at the start of the first input.
                let start = geometry::trajectory::nearest(&truth, t0 - u0.dt_s).copied().unwrap_or(truth[0].1);
                let dr = dead_reckoning(&start, &st.inputs);
                geometry::tum::write_tum(&out_dir.join("dead_reckoning.tum"), dr.iter().map(|(t, p)| (*t, p)))?;
                let dr_p: Vec<_> = dr.iter().map(|(t, p)| (*t, p.translation.vector)).collect();
                let dr_ate = ate_nearest(&dr_p, &truth_p, planar);
                ates.dead_reckoning = finite(dr_ate);
                tracing::info!(
                    "ATE ({}, nearest stamp, every ground-truth row): buoy EKF {ate:.3} m, dead reckoning {dr_ate:.3} m",
                    if planar { "2-D" } else { "3-D" }
                );
            } else {
                tracing::info!("ATE (nearest stamp, every ground-truth row): buoy EKF {ate:.3} m");
            }
            part.ate_m = Some(ates);
        }
        Ok(_) => tracing::info!("no accuracy evaluation: {} is empty", gt_path.display()),
        Err(e) => tracing::info!("no accuracy evaluation: {e}"),
    }
    Ok(part)
}

/// The NIS test of the ranges taken: (sum of ν²/S, count) → mean, interval, verdict.
fn range_nis((sum, n): (f64, u64)) -> Option<RangeNis> {
    let (lo, hi) = geometry::stats::mean_chi2_interval(1, usize::try_from(n).ok()?, 0.95)?;
    let mean = sum / n as f64;
    tracing::info!(
        "range NIS {mean:.2} over {n} ranges taken (χ²₁ each: consistent within [{lo:.3}, {hi:.3}] at 95 %: {})",
        if (lo..=hi).contains(&mean) {
            "yes"
        } else if mean < lo {
            "no, the innovations' covariance is too large"
        } else {
            "no, the innovations' covariance is too small"
        }
    );
    Some(RangeNis { mean: finite(mean), samples: n, interval_95: [lo, hi], consistent: (lo..=hi).contains(&mean) })
}
