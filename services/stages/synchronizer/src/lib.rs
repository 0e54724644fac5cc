//! The `synchronizer` process's settings and its pure `step` logic: buoy fixes go into a
//! [`timesync::Synchronizer`]; each SLAM pose waits (up to `sync.max_latency_s` of wall time since it
//! arrived) for a fix after its stamp, then is paired with the buoy position interpolated to its
//! stamp (EQUATIONS §5.1: 3-point Lagrange, eq 30 covariance), or extrapolated and flagged.
//! [`stage::SynchronizerStage`] is the stage around it; `main.rs` one line.

pub mod stage;
pub mod summary;

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use nalgebra::{Matrix3, Vector3};
use pipeline_runtime::Validate;
use pipeline_runtime::{Issues, ProcessSettings};
use serde::{Deserialize, Serialize};
use shared_types::{BuoyFix, MsgHeader, PoseEstimate};
use timesync::{CrossPrev, Fix, SyncConfig, SyncDecision, SyncResult, Synchronizer};

/// Settings of the `synchronizer` process.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SynchronizerSettings {
    /// The buffer and waiting policy (`capacity`, `max_gap_s`, `max_latency_s`,
    /// `max_extrapolation_s`, `extrapolation_velocity_sigma_mps`, `duplicate_tolerance_s`,
    /// `restart_backjump_s`): documented in the `timesync` crate (algorithms/timesync). `max_latency_s` is
    /// the longest a pose waits, in wall time since it arrived, for a fix after its stamp.
    pub sync: SyncConfig,
    /// The processes whose end of stream ends this one's input (the SLAM and buoy stages): it
    /// flushes and ends once all of them have ended. Empty: the first end of stream received.
    pub end_after: Vec<String>,
    /// Send, as soon as a SLAM pose arrives and has to wait for the fix after it, a predicted
    /// pair (flag `SYNC_PREDICTED`: the buoy position extrapolated from the newest fix), so that
    /// fusion publishes a first pose at once; the pair proper follows as before.
    pub predict: bool,
}

impl Default for SynchronizerSettings {
    fn default() -> Self {
        Self { sync: SyncConfig::default(), end_after: vec!["slam".into(), "buoy".into()], predict: true }
    }
}

impl ProcessSettings for SynchronizerSettings {
    fn shm_estimate_bytes(&self, _extra_subscribers: usize) -> u64 {
        1 << 20
    }
}

impl Validate for SynchronizerSettings {
    fn validate(&self, issues: &mut Issues) {
        issues.nested("sync", &self.sync);
    }
}

/// A pose waiting for its buoy position.
#[derive(Debug, Clone)]
pub struct PendingPose {
    /// Its header.
    pub header: MsgHeader,
    /// The SLAM pose.
    pub pose: PoseEstimate,
    /// When it arrived (wall clock).
    pub arrived: Instant,
}

/// A pose paired with the buoy position at its stamp.
#[derive(Debug, Clone)]
pub struct Paired {
    /// The pose's header.
    pub header: MsgHeader,
    /// The SLAM pose.
    pub pose: PoseEstimate,
    /// The buoy position at the pose's stamp.
    pub buoy: SyncResult,
    /// Wall time the pose spent here, s.
    pub added_latency_s: f64,
    /// A prediction (`SYNC_PREDICTED`), sent when the pose arrived; its pair proper follows.
    pub predicted: bool,
}

/// Counts of what happened to the poses and fixes.
#[derive(Debug, Clone, Default, Serialize, Deserialize, schemars::JsonSchema)]
pub struct SyncStats {
    /// Poses paired by interpolation (quadratic, linear or an exact fix).
    pub interpolated: u64,
    /// ... of which linear.
    pub linear: u64,
    /// ... of which with the fixes' cross-covariances (docs/EQUATIONS.md §5.1a; the others by
    /// [3D] eq 30, as independent fixes: a fix without its link to the one before, from an
    /// estimator that does not give it, after a re-start or a lost fix).
    pub correlated: u64,
    /// Poses paired by extrapolation.
    pub extrapolated: u64,
    /// Poses with a gap between the fixes around them.
    pub gap: u64,
    /// Poses with no usable buoy position (dropped, counted).
    pub unavailable: u64,
    /// Fixes rejected (NaN, a covariance that is not positive semi-definite).
    pub invalid_fixes: u64,
    /// Poses rejected (NaN stamp or position).
    pub invalid_poses: u64,
    /// Predicted pairs sent (one per pose that had to wait, when a fix was near enough to
    /// extrapolate from); not counted in the kinds above, which count the pairs proper.
    pub predicted: u64,
}

/// The process state.
pub struct SyncState {
    sync: Synchronizer,
    max_latency: Duration,
    /// Poses waiting, in arrival order.
    pub pending: VecDeque<PendingPose>,
    /// Counters.
    pub stats: SyncStats,
    /// Added latency of each published pair, s.
    pub added_latency_s: Vec<f64>,
}

impl SyncState {
    /// A new state; the settings must validate.
    pub fn new(settings: &SynchronizerSettings) -> Result<Self, Vec<pipeline_runtime::ConfigIssue>> {
        Ok(Self {
            sync: Synchronizer::new(settings.sync.clone())?,
            max_latency: Duration::from_secs_f64(settings.sync.max_latency_s),
            pending: VecDeque::new(),
            stats: SyncStats::default(),
            added_latency_s: vec![],
        })
    }

    /// The synchronizer (its buffer and counters).
    pub fn synchronizer(&self) -> &Synchronizer {
        &self.sync
    }

    /// Adds a buoy fix.
    pub fn push_fix(&mut self, header: &MsgHeader, fix: &BuoyFix) {
        let f = Fix {
            t_s: header.stamp_ns as f64 / 1e9,
            seq: header.seq,
            position_m: Vector3::from(fix.position_m),
            covariance_m2: Matrix3::from_row_slice(&fix.covariance_m2),
            velocity_mps: Vector3::from(fix.velocity_mps),
            cross_prev: (fix.prev_fix_stamp_ns != 0).then(|| CrossPrev {
                prev_t_s: fix.prev_fix_stamp_ns as f64 / 1e9,
                covariance_m2: Matrix3::from_row_slice(&fix.cross_covariance_prev_m2),
            }),
        };
        if self.sync.insert(f).is_err() {
            self.stats.invalid_fixes += 1;
        }
    }

    /// Queues a SLAM pose.
    pub fn push_pose(&mut self, header: MsgHeader, pose: PoseEstimate, now: Instant) {
        if !pose.position_m.iter().all(|v| v.is_finite()) {
            self.stats.invalid_poses += 1;
            return;
        }
        self.pending.push_back(PendingPose { header, pose, arrived: now });
    }

    /// The predicted pair of a pose that has to wait for the fix after it (`None` when it need not
    /// wait, when poses queue before it, or when no fix is near enough to extrapolate from).
    pub fn predict(&mut self, header: &MsgHeader, pose: &PoseEstimate) -> Option<Paired> {
        if !pose.position_m.iter().all(|v| v.is_finite()) {
            return None;
        }
        let t_s = header.stamp_ns as f64 / 1e9;
        // Paired at once (a fix after it is here): no prediction needed.
        if !matches!(self.sync.try_sync(t_s, t_s), Ok(SyncDecision::Wait { .. })) {
            return None;
        }
        let past_wait = t_s + self.max_latency.as_secs_f64() + 1.0;
        match self.sync.try_sync(t_s, past_wait) {
            Ok(SyncDecision::Ready(r) | SyncDecision::Extrapolated(r)) => {
                Some(Paired { header: *header, pose: *pose, buoy: r, added_latency_s: 0.0, predicted: true })
            }
            _ => None,
        }
    }

    /// When the oldest waiting pose stops waiting.
    pub fn next_deadline(&self) -> Option<Instant> {
        self.pending.front().map(|p| p.arrived + self.max_latency)
    }

    /// The process's `step`: pairs every waiting pose whose buoy position is available, in
    /// arrival order (a pose still waiting holds back the ones behind it, so pairs leave in
    /// order). `flush` (the inputs ended) ends every wait.
    pub fn step(&mut self, now: Instant, flush: bool) -> Vec<Paired> {
        let mut out = vec![];
        while let Some(p) = self.pending.front() {
            let t_s = p.header.stamp_ns as f64 / 1e9;
            let waited = now.saturating_duration_since(p.arrived);
            // The wait is measured on the wall clock from the pose's arrival, mapped onto the
            // stamp's clock for the policy: now_s = t_k + waited.
            let now_s = if flush { f64::INFINITY } else { t_s + waited.as_secs_f64() };
            let decision = match self.sync.try_sync(t_s, now_s.min(f64::MAX)) {
                Ok(d) => d,
                Err(_) => {
                    self.stats.invalid_poses += 1;
                    self.pending.pop_front();
                    continue;
                }
            };
            let result = match decision {
                SyncDecision::Wait { .. } => break,
                SyncDecision::Ready(r) | SyncDecision::Extrapolated(r) => r,
                SyncDecision::Unavailable(_) => {
                    self.stats.unavailable += 1;
                    self.pending.pop_front();
                    continue;
                }
            };
            let p = self.pending.pop_front().expect("front exists");
            let f = result.flags;
            self.stats.interpolated += u64::from(!f.extrapolated);
            self.stats.linear += u64::from(f.linear);
            self.stats.correlated += u64::from(result.correlated);
            self.stats.extrapolated += u64::from(f.extrapolated);
            self.stats.gap += u64::from(f.gap);
            self.added_latency_s.push(waited.as_secs_f64());
            out.push(Paired {
                header: p.header,
                pose: p.pose,
                buoy: result,
                added_latency_s: waited.as_secs_f64(),
                predicted: false,
            });
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(stamp_s: f64, seq: u64) -> MsgHeader {
        MsgHeader { stamp_ns: (stamp_s * 1e9) as u64, seq, ..Default::default() }
    }

    fn fix_at(t: f64) -> BuoyFix {
        BuoyFix {
            position_m: [t, 2.0 * t, 0.0],
            covariance_m2: [0.1, 0.0, 0.0, 0.0, 0.1, 0.0, 0.0, 0.0, 0.1],
            velocity_mps: [1.0, 2.0, 0.0],
            ranges_used: 4,
            ranges_rejected: 0,
            ..Default::default()
        }
    }

    fn pose() -> PoseEstimate {
        PoseEstimate { orientation_xyzw: [0.0, 0.0, 0.0, 1.0], ..Default::default() }
    }

    #[test]
    fn a_pose_waits_for_a_bracketing_fix_then_is_interpolated() {
        let st_settings = SynchronizerSettings::default();
        let mut st = SyncState::new(&st_settings).unwrap();
        let t0 = Instant::now();
        st.push_fix(&header(1.0, 0), &fix_at(1.0));
        st.push_fix(&header(2.0, 1), &fix_at(2.0));
        st.push_pose(header(2.5, 0), pose(), t0);
        assert!(st.step(t0, false).is_empty(), "no fix after 2.5 s yet: wait");
        assert_eq!(st.next_deadline(), Some(t0 + Duration::from_secs_f64(st_settings.sync.max_latency_s)));
        st.push_fix(&header(3.0, 2), &fix_at(3.0));
        let out = st.step(t0 + Duration::from_millis(10), false);
        assert_eq!(out.len(), 1);
        let b = &out[0].buoy;
        assert!(!b.flags.extrapolated && b.flags.interpolated);
        assert!((b.position_m - Vector3::new(2.5, 5.0, 0.0)).norm() < 1e-9, "{}", b.position_m);
        assert!((out[0].added_latency_s - 0.01).abs() < 1e-6);
    }

    /// Fixes that bring their cross-covariance with the fix before (ρ = 0.9 here) give the pair
    /// the covariance of the correlated sum, larger than eq 30's, and are counted; a fix whose
    /// link names another fix than the one before it is taken as independent (eq 30).
    #[test]
    fn fixes_with_their_cross_covariance_give_the_correlated_covariance() {
        let linked = |t: f64| BuoyFix {
            prev_fix_stamp_ns: ((t - 1.0) * 1e9) as u64,
            cross_covariance_prev_m2: [0.09, 0.0, 0.0, 0.0, 0.09, 0.0, 0.0, 0.0, 0.09],
            ..fix_at(t)
        };
        let run = |fixes: [BuoyFix; 3]| {
            let mut st = SyncState::new(&SynchronizerSettings::default()).unwrap();
            let t0 = Instant::now();
            for (k, f) in fixes.iter().enumerate() {
                st.push_fix(&header(1.0 + k as f64, k as u64), f);
            }
            st.push_pose(header(2.5, 0), pose(), t0);
            let out = st.step(t0, false);
            assert_eq!(out.len(), 1);
            (out[0].buoy.covariance_m2[(0, 0)], st.stats.correlated)
        };
        let (independent, n0) = run([fix_at(1.0), fix_at(2.0), fix_at(3.0)]);
        let (correlated, n1) = run([fix_at(1.0), linked(2.0), linked(3.0)]);
        let (broken, n2) = run([fix_at(1.0), BuoyFix { prev_fix_stamp_ns: 1_500_000_000, ..linked(2.0) }, linked(3.0)]);
        assert_eq!((n0, n1, n2), (0, 1, 0));
        // Weights at 2.5 s of fixes at 1, 2, 3 s: (−1/8, 3/4, 3/8); eq 30 gives Σξ²·0.1.
        let w = [-0.125, 0.75, 0.375];
        let eq30 = w.iter().map(|x| x * x).sum::<f64>() * 0.1;
        assert!((independent - eq30).abs() < 1e-12 && (broken - eq30).abs() < 1e-12, "{independent} {broken}");
        // With ρ = 0.9 between neighbours and 0.81 across two (0.09·0.1⁻¹·0.09).
        let corr = eq30 + 2.0 * (w[0] * w[1] * 0.09 + w[1] * w[2] * 0.09 + w[0] * w[2] * 0.081);
        assert!((correlated - corr).abs() < 1e-12, "{correlated} against {corr}");
    }

    #[test]
    fn after_the_wait_the_pose_is_extrapolated_and_flagged() {
        let mut st = SyncState::new(&SynchronizerSettings::default()).unwrap();
        let t0 = Instant::now();
        st.push_fix(&header(1.0, 0), &fix_at(1.0));
        st.push_fix(&header(2.0, 1), &fix_at(2.0));
        st.push_pose(header(2.5, 0), pose(), t0);
        st.push_pose(header(2.6, 1), pose(), t0);
        assert!(st.step(t0 + Duration::from_millis(500), false).is_empty());
        let out = st.step(t0 + Duration::from_millis(1001), false);
        assert_eq!(out.len(), 2, "both waited out");
        assert!(out.iter().all(|p| p.buoy.flags.extrapolated));
        assert!((out[0].buoy.position_m - Vector3::new(2.5, 5.0, 0.0)).norm() < 1e-9, "velocity extrapolation");
        assert!(out[0].buoy.covariance_m2[(0, 0)] > 0.1, "inflated");
        assert_eq!(st.stats.extrapolated, 2);
    }

    #[test]
    fn flush_ends_every_wait_and_bad_inputs_are_counted() {
        let mut st = SyncState::new(&SynchronizerSettings::default()).unwrap();
        let t0 = Instant::now();
        let mut bad = fix_at(1.0);
        bad.position_m[0] = f64::NAN;
        st.push_fix(&header(1.0, 0), &bad);
        assert_eq!(st.stats.invalid_fixes, 1);
        st.push_pose(header(1.0, 0), pose(), t0);
        let mut nan_pose = pose();
        nan_pose.position_m[1] = f64::NAN;
        st.push_pose(header(1.1, 1), nan_pose, t0);
        assert_eq!(st.stats.invalid_poses, 1);
        assert!(st.step(t0, false).is_empty(), "no fixes yet: wait");
        assert!(st.step(t0, true).is_empty(), "flushed without any fix: unavailable");
        assert_eq!(st.stats.unavailable, 1);
        assert!(st.pending.is_empty());
    }
}
