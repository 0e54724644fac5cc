//! The `buoy_ekf` process's settings and its pure `step` logic: odometry, buoy ranges and depth
//! readings applied to the [`buoy::BuoyEkf`] in stamp order, one [`Fix`] per ranges message, and
//! the end-of-run evaluation (dead reckoning and the ATE of both against the ground truth).
//! [`stage::BuoyEkfStage`] is the stage around it; `main.rs` one line.

use std::collections::VecDeque;

pub mod journal;
pub mod stage;
pub mod summary;
use std::time::{Duration, Instant};

use buoy::{BuoyConfig, BuoyEkf, Estimate, Mode, RangeOutcome};
use geometry::ProcessInput;
use nalgebra::{Isometry3, Matrix3, Translation3, UnitQuaternion, Vector3};
use pipeline_runtime::Validate;
use pipeline_runtime::{Issues, ProcessSettings};
use serde::{Deserialize, Serialize};
use shared_types::{BuoyRange, DepthReading, OdometryInput};

/// Settings of the `buoy_ekf` process.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BuoyEkfSettings {
    /// The estimator (buoy table, mode, noise, gate, biases, initialisation): every key is
    /// documented in `algorithms/buoy/src/config.rs`.
    pub ekf: BuoyConfig,
    /// Predict with the odometry stream. Ranges then wait (up to `odometry_wait_s`) until
    /// odometry up to their stamp has arrived, so that they are applied in stamp order.
    pub use_odometry: bool,
    /// Use pressure depth readings (spatial mode).
    pub use_depth: bool,
    /// Longest a range waits for odometry up to its stamp before it is applied without, in
    /// data time, s: once another input (depth, later ranges) is this far past the range's stamp
    /// and odometry is not, the odometry source has stalled and the range goes. Data time, so
    /// that a replay gives the same fixes however loaded the machine is.
    pub odometry_wait_s: f64,
    /// The same in wall time, s, for when every input stalls (a live source that stops): a range
    /// waits at most this long after it arrived (0 = no limit: only data time and the end of
    /// the stream release it).
    pub odometry_stall_s: f64,
    /// Ground truth to evaluate against at the end (TUM; relative to the output directory);
    /// skipped when missing.
    pub ground_truth: String,
}

impl Default for BuoyEkfSettings {
    fn default() -> Self {
        Self {
            ekf: BuoyConfig::default(),
            use_odometry: true,
            use_depth: true,
            odometry_wait_s: 0.5,
            odometry_stall_s: 5.0,
            ground_truth: "ground_truth.tum".into(),
        }
    }
}

impl ProcessSettings for BuoyEkfSettings {
    fn shm_estimate_bytes(&self, _extra_subscribers: usize) -> u64 {
        // One BuoyFix stream.
        1 << 20
    }
}

impl Validate for BuoyEkfSettings {
    fn validate(&self, issues: &mut Issues) {
        issues.nested("ekf", &self.ekf);
        issues.check(
            !self.ekf.needs_depth() || self.use_depth,
            "use_depth",
            "is false, but the buoys lie in one plane (or there are fewer than 4) in spatial mode: a fix has a \
             mirror image across that plane and only depth readings pick the side; set use_depth = true, add a buoy \
             off the plane, or use mode = \"planar\"",
        );
        issues.check(
            self.odometry_wait_s.is_finite() && self.odometry_wait_s >= 0.0,
            "odometry_wait_s",
            "must be >= 0",
        );
        issues.check(
            self.odometry_stall_s.is_finite() && self.odometry_stall_s >= 0.0,
            "odometry_stall_s",
            "must be >= 0 (0: no wall-time limit)",
        );
    }
}

/// A fix to publish: the estimate after a ranges message.
#[derive(Debug, Clone)]
pub struct Fix {
    /// Stamp of the ranges message, ns.
    pub stamp_ns: u64,
    /// Its origin time (end-to-end latency), ns.
    pub origin_ns: u64,
    /// The estimate at the stamp.
    pub estimate: Estimate,
    /// Ranges of the message accepted.
    pub used: u32,
    /// Ranges of the message rejected (gate, invalid, unknown buoy).
    pub rejected: u32,
    /// The stamp of the fix published before this one (ns) and the cross-covariance of that
    /// fix's position error with this one's, cov(e_prev, e_this) (m², the filter's model,
    /// [`buoy::BuoyEkf::mark_fix`]); `None` after a re-start, a reset or while the heading is a
    /// mixture.
    pub cross_prev: Option<(u64, Matrix3<f64>)>,
}

/// An input as the filter took it, in the order it took them: the journal's unit. Replaying
/// them in order ([`BuoyState::replay`]) rebuilds the filter exactly as it was (a restarted
/// instance goes on from the killed one's state instead of starting over).
#[derive(Debug, Clone, PartialEq)]
pub enum Applied {
    /// An odometry message.
    Odometry {
        /// Its stamp, ns.
        stamp_ns: u64,
        /// The message.
        input: OdometryInput,
    },
    /// A ranges message.
    Ranges {
        /// Its stamp, ns.
        stamp_ns: u64,
        /// Its origin time, ns.
        origin_ns: u64,
        /// The ranges.
        ranges: Vec<BuoyRange>,
    },
    /// A depth reading.
    Depth {
        /// Its stamp, ns.
        stamp_ns: u64,
        /// The reading.
        reading: DepthReading,
    },
}

struct PendingRanges {
    stamp_ns: u64,
    origin_ns: u64,
    ranges: Vec<BuoyRange>,
    received: Instant,
}

/// One estimate of the filter, in the world frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrajectorySample {
    /// Stamp, s.
    pub t_s: f64,
    /// Position, m.
    pub position_m: Vector3<f64>,
    /// Heading, rad, once known.
    pub heading_rad: Option<f64>,
    /// Covariance of the position, m².
    pub covariance_m2: Matrix3<f64>,
}

impl TrajectorySample {
    fn of(t_s: f64, e: &buoy::Estimate) -> Self {
        Self { t_s, position_m: e.position_m, heading_rad: e.heading_rad, covariance_m2: e.covariance_m2 }
    }
}

/// The process state around the estimator: input ordering, the trajectory and counters.
pub struct BuoyState {
    settings: BuoyEkfSettings,
    ekf: Option<BuoyEkf>,
    odometry: VecDeque<(u64, OdometryInput)>,
    ranges: VecDeque<PendingRanges>,
    depth: VecDeque<(u64, DepthReading)>,
    newest_odometry_ns: Option<u64>,
    /// Newest stamp of any input, ns.
    newest_stamp_ns: Option<u64>,
    /// `newest_stamp_ns` as it was at the previous [`BuoyState::step`]: the data-time evidence
    /// that odometry has stalled. The stage receives odometry first and ranges after, so ranges
    /// received in this round may be newer than odometry that was published before them but
    /// after the odometry was received; by the next round that odometry has been received too.
    settled_newest_ns: Option<u64>,
    /// Every odometry input applied, with its stamp (for dead reckoning).
    pub inputs: Vec<(f64, ProcessInput)>,
    /// The estimate after every odometry input and every ranges message once initialised:
    /// Fixes are published at the buoy rate only; this is the filter's estimate at every time it
    /// has one (the ATE, the NEES and `buoy_ekf.tum`).
    pub trajectory: Vec<TrajectorySample>,
    /// Messages or values rejected before the filter (NaN, out of order), by reason.
    pub invalid: std::collections::BTreeMap<String, u64>,
    /// Errors the filter returned (unknown buoy, non-finite, not positive definite), by message.
    pub filter_errors: std::collections::BTreeMap<String, u64>,
    /// Ranges buffered while the filter waited for a usable trilateration.
    pub waiting: u64,
    /// Why the filter is still waiting (the last trilateration's failure), once it waited.
    pub waiting_reason: Option<String>,
    /// When the last "still waiting" warning went out (one every [`WAIT_WARN_EVERY`]).
    waiting_warned: Option<Instant>,
    /// Data time of the first range that had to wait, s.
    waiting_since_s: Option<f64>,
    /// Time of the last event applied, ns.
    last_ns: Option<u64>,
    /// Stamp of the last fix published, ns.
    last_fix_ns: Option<u64>,
    /// The inputs taken since the last [`BuoyState::take_applied`] (for the journal).
    applied: Vec<Applied>,
    /// Replaying a journal: the log stays quiet (the killed instance said it all already).
    replaying: bool,
    /// Sum and count of the normalised innovations ν²/S of the ranges the filter took (the NIS
    /// test, `buoy_ekf.range_nis`).
    pub range_nis: (f64, u64),
    /// The attitude the odometry's rotation increments build, for the world yaw increment and
    /// the horizontal speed (`ekf.motion.level_time_constant_s`).
    attitude: buoy::attitude::LevelledAttitude,
}

/// Wall time between two warnings that the filter still waits for its initialisation.
pub const WAIT_WARN_EVERY: Duration = Duration::from_secs(5);

/// Data time the filter may wait for its initialisation before the first warning, s (a start
/// needs a few ranges, a depth reading, or with the odometry window, a few metres of path).
pub const WAIT_WARN_AFTER_S: f64 = 10.0;

fn stamp_s(ns: u64) -> f64 {
    ns as f64 / 1e9
}

impl BuoyState {
    /// A new state; the estimator starts at the first message's stamp.
    pub fn new(settings: BuoyEkfSettings) -> Self {
        let attitude = buoy::attitude::LevelledAttitude::new(settings.ekf.motion.level_time_constant_s);
        Self {
            attitude,
            range_nis: (0.0, 0),
            settings,
            ekf: None,
            odometry: VecDeque::new(),
            ranges: VecDeque::new(),
            depth: VecDeque::new(),
            newest_odometry_ns: None,
            newest_stamp_ns: None,
            settled_newest_ns: None,
            inputs: vec![],
            trajectory: vec![],
            invalid: Default::default(),
            filter_errors: Default::default(),
            waiting: 0,
            waiting_reason: None,
            waiting_warned: None,
            waiting_since_s: None,
            last_ns: None,
            last_fix_ns: None,
            applied: vec![],
            replaying: false,
        }
    }

    /// The inputs the filter took since the last call, in the order it took them.
    pub fn take_applied(&mut self) -> Vec<Applied> {
        std::mem::take(&mut self.applied)
    }

    /// Takes `inputs` (a killed instance's journal, [`BuoyState::take_applied`]) as they were
    /// taken then, without publishing: the filter, trajectory and counters end up as the killed
    /// instance left them. Returns the fixes it had published.
    pub fn replay(&mut self, inputs: Vec<Applied>) -> Vec<Fix> {
        self.replaying = true;
        let mut fixes = vec![];
        for a in inputs {
            match a {
                Applied::Odometry { stamp_ns, input } => {
                    if self.settings.use_odometry {
                        self.newest_odometry_ns = Some(self.newest_odometry_ns.map_or(stamp_ns, |s| s.max(stamp_ns)));
                    }
                    self.saw(stamp_ns);
                    self.apply_odometry(stamp_ns, &input);
                }
                Applied::Ranges { stamp_ns, origin_ns, ranges } => {
                    self.saw(stamp_ns);
                    let r = PendingRanges { stamp_ns, origin_ns, ranges, received: Instant::now() };
                    fixes.extend(self.apply_ranges(r));
                }
                Applied::Depth { stamp_ns, reading } => {
                    self.saw(stamp_ns);
                    self.apply_depth(stamp_ns, &reading);
                }
            }
        }
        self.settled_newest_ns = self.newest_stamp_ns;
        self.applied.clear();
        self.replaying = false;
        fixes
    }

    /// The estimator, once the first message has started it.
    pub fn ekf(&self) -> Option<&BuoyEkf> {
        self.ekf.as_ref()
    }

    fn count(map: &mut std::collections::BTreeMap<String, u64>, reason: String) {
        *map.entry(reason).or_default() += 1;
    }

    /// Queues an odometry message (ignored unless `use_odometry`).
    pub fn push_odometry(&mut self, stamp_ns: u64, u: &OdometryInput) {
        if !self.settings.use_odometry {
            return;
        }
        self.saw(stamp_ns);
        self.newest_odometry_ns = Some(self.newest_odometry_ns.map_or(stamp_ns, |s| s.max(stamp_ns)));
        self.odometry.push_back((stamp_ns, *u));
    }

    /// Queues a ranges message.
    pub fn push_ranges(&mut self, stamp_ns: u64, origin_ns: u64, ranges: &[BuoyRange], now: Instant) {
        self.saw(stamp_ns);
        self.ranges.push_back(PendingRanges { stamp_ns, origin_ns, ranges: ranges.to_vec(), received: now });
    }

    /// Queues a depth reading (ignored unless `use_depth` in spatial mode).
    pub fn push_depth(&mut self, stamp_ns: u64, d: &DepthReading) {
        self.saw(stamp_ns);
        if self.settings.use_depth && self.settings.ekf.mode == Mode::Spatial {
            self.depth.push_back((stamp_ns, *d));
        }
    }

    fn saw(&mut self, stamp_ns: u64) {
        self.newest_stamp_ns = Some(self.newest_stamp_ns.map_or(stamp_ns, |s| s.max(stamp_ns)));
    }

    /// Messages waiting, per input: (odometry, ranges, depth).
    pub fn held(&self) -> (usize, usize, usize) {
        (self.odometry.len(), self.ranges.len(), self.depth.len())
    }

    /// Messages waiting.
    pub fn pending(&self) -> usize {
        self.odometry.len() + self.ranges.len() + self.depth.len()
    }

    /// When the oldest waiting ranges message stops waiting for odometry in wall time (for a
    /// wake-up; `None` without a wall-time limit).
    pub fn next_deadline(&self) -> Option<Instant> {
        let stall = self.settings.odometry_stall_s;
        (stall > 0.0).then(|| self.ranges.front().map(|r| r.received + Duration::from_secs_f64(stall))).flatten()
    }

    fn ekf_at(&mut self, t_s: f64) -> Result<&mut BuoyEkf, String> {
        if self.ekf.is_none() {
            self.ekf = Some(BuoyEkf::new(self.settings.ekf.clone(), t_s).map_err(|e| e.to_string())?);
        }
        Ok(self.ekf.as_mut().expect("just made"))
    }

    /// The process's `step`: applies the queued messages in stamp order and returns the fixes
    /// to publish. A ranges message waits for odometry up to its stamp (unless `flush`, at the
    /// end of the stream, or it has waited `odometry_wait_s`). Called once per round of
    /// receiving (odometry first); the data-time evidence that odometry stalled is taken from
    /// the rounds before this one.
    pub fn step(&mut self, flush: bool, now: Instant) -> Vec<Fix> {
        let mut out = vec![];
        // Everything up to the horizon is applied in stamp order: the newest odometry stamp, or
        // the stamp of the newest ranges message that has waited long enough, or everything.
        // Data time: ranges that other inputs have left `odometry_wait_s` behind. Wall time:
        // ranges that have waited `odometry_stall_s` (every input stalled).
        let wait_ns = (self.settings.odometry_wait_s * 1e9) as u64;
        let newest = self.settled_newest_ns.unwrap_or(0);
        self.settled_newest_ns = self.newest_stamp_ns;
        let stall = Duration::from_secs_f64(self.settings.odometry_stall_s);
        let waited_out = self
            .ranges
            .iter()
            .filter(|r| {
                r.stamp_ns.saturating_add(wait_ns) <= newest
                    || (stall > Duration::ZERO && now.saturating_duration_since(r.received) >= stall)
            })
            .map(|r| r.stamp_ns)
            .max();
        let horizon = if flush || !self.settings.use_odometry {
            u64::MAX
        } else {
            self.newest_odometry_ns.into_iter().chain(waited_out).max().unwrap_or(0)
        };
        loop {
            let t_odo = self.odometry.front().map(|(s, _)| *s);
            let t_rng = self.ranges.front().map(|r| r.stamp_ns);
            let t_dep = self.depth.front().map(|(s, _)| *s);
            let Some(t) = [t_odo, t_rng, t_dep].into_iter().flatten().min() else { break };
            if t > horizon {
                break;
            }
            if t_odo == Some(t) {
                let (stamp, u) = self.odometry.pop_front().expect("front exists");
                self.applied.push(Applied::Odometry { stamp_ns: stamp, input: u });
                self.apply_odometry(stamp, &u);
            } else if t_rng == Some(t) {
                let r = self.ranges.pop_front().expect("front exists");
                self.applied.push(Applied::Ranges {
                    stamp_ns: r.stamp_ns,
                    origin_ns: r.origin_ns,
                    ranges: r.ranges.clone(),
                });
                if let Some(fix) = self.apply_ranges(r) {
                    out.push(fix);
                }
            } else {
                let (stamp, d) = self.depth.pop_front().expect("front exists");
                self.applied.push(Applied::Depth { stamp_ns: stamp, reading: d });
                self.apply_depth(stamp, &d);
            }
        }
        out
    }

    /// Records the estimate at `t` (after an odometry input, once initialised) in the trajectory.
    fn record(&mut self, t: f64) {
        if let Some(Ok(e)) = self.ekf.as_ref().filter(|e| e.is_initialised()).map(|e| e.estimate()) {
            self.trajectory.push(TrajectorySample::of(t, &e));
        }
    }

    /// Stamps must not go back: a message older than the last applied one is dropped (counted).
    fn in_order(&mut self, stamp_ns: u64, what: &str) -> bool {
        if self.last_ns.is_some_and(|l| stamp_ns < l) {
            Self::count(&mut self.invalid, format!("{what} older than the last message applied"));
            return false;
        }
        self.last_ns = Some(stamp_ns);
        true
    }

    fn apply_odometry(&mut self, stamp_ns: u64, u: &OdometryInput) {
        let ok = u.dt_s.is_finite()
            && u.dt_s > 0.0
            && u.v_mps.is_finite()
            && u.delta_theta_rad.iter().all(|v| v.is_finite())
            && u.input_covariance[0].is_finite()
            && u.input_covariance[15].is_finite();
        if !ok {
            Self::count(&mut self.invalid, "odometry with NaN or dt <= 0".into());
            return;
        }
        if !self.in_order(stamp_ns, "odometry") {
            return;
        }
        let t = stamp_s(stamp_ns);
        self.inputs.push((
            t,
            ProcessInput { v_mps: u.v_mps, delta_theta_rad: Vector3::from(u.delta_theta_rad), dt_s: u.dt_s },
        ));
        // The body-frame increments in the filter's planar terms (world yaw, horizontal speed).
        let planar = self.attitude.step(&Vector3::from(u.delta_theta_rad), u.dt_s);
        let input = buoy::OdometryInput {
            dt_s: u.dt_s,
            v_mps: u.v_mps * planar.horizontal_fraction,
            dtheta_rad: planar.yaw_increment_rad,
            var_v: u.input_covariance[0].max(0.0) * planar.horizontal_fraction.powi(2),
            var_dtheta: u.input_covariance[15].max(0.0),
        };
        let result =
            self.ekf_at(t - u.dt_s).and_then(|ekf| ekf.predict_with_input(t, &input).map_err(|e| e.to_string()));
        match result {
            Err(e) => Self::count(&mut self.filter_errors, format!("odometry: {e}")),
            Ok(()) => self.record(t),
        }
    }

    fn apply_depth(&mut self, stamp_ns: u64, d: &DepthReading) {
        if !(d.depth_m.is_finite() && d.sigma_m.is_finite() && d.sigma_m > 0.0) {
            Self::count(&mut self.invalid, "depth with NaN or sigma <= 0".into());
            return;
        }
        if !self.in_order(stamp_ns, "depth") {
            return;
        }
        let t = stamp_s(stamp_ns);
        let result = self.ekf_at(t).and_then(|ekf| {
            ekf.predict_to(t).map_err(|e| e.to_string())?;
            ekf.update_depth(d.depth_m, d.sigma_m).map_err(|e| e.to_string())
        });
        if let Err(e) = result {
            Self::count(&mut self.filter_errors, format!("depth: {e}"));
        }
    }

    fn apply_ranges(&mut self, r: PendingRanges) -> Option<Fix> {
        if !self.in_order(r.stamp_ns, "ranges") {
            return None;
        }
        let t = stamp_s(r.stamp_ns);
        let (mut used, mut rejected) = (0u32, 0u32);
        let quiet = self.replaying;
        let ekf = match self.ekf_at(t) {
            Ok(e) => e,
            Err(e) => {
                Self::count(&mut self.filter_errors, format!("start: {e}"));
                return None;
            }
        };
        if let Err(e) = ekf.predict_to(t) {
            Self::count(&mut self.filter_errors, format!("predict: {e}"));
            return None;
        }
        let mut errors = vec![];
        let mut waiting = 0;
        let mut reason = None;
        let restarts_before = ekf.counters().reinitialisations;
        let switches_before = ekf.counters().outlier_branch_switches;
        let corrections_before = ekf.counters().start_corrections;
        let mut nis_taken = (0.0, 0u64);
        for b in &r.ranges {
            match ekf.update_range(b.buoy_id, b.range_m, b.sigma_m) {
                Ok(RangeOutcome::Accepted { nis, .. }) => {
                    used += 1;
                    if nis.is_finite() {
                        nis_taken.0 += nis;
                        nis_taken.1 += 1;
                    }
                }
                Ok(RangeOutcome::Initialised) => used += 1,
                Ok(RangeOutcome::Rejected { .. }) => rejected += 1,
                Ok(RangeOutcome::Waiting(why)) => {
                    waiting += 1;
                    reason = Some(why.to_string());
                }
                Err(e) => {
                    rejected += 1;
                    errors.push(format!("range: {e}"));
                }
            }
        }
        let estimate = ekf.is_initialised().then(|| ekf.estimate());
        // A fix is published with this estimate: the filter marks it, and gives its error's
        // cross-covariance with the fix before.
        let cross = match &estimate {
            Some(Ok(_)) => ekf.mark_fix(),
            _ => None,
        };
        if ekf.counters().reinitialisations > restarts_before && !quiet {
            tracing::warn!(
                data_time_s = t,
                restarts = ekf.counters().reinitialisations,
                "the buoy EKF was lost (too many ranges rejected) and re-started from a robust fix over its \
                 odometry window (`ekf.recovery.check_rejected_share`, `ekf.init.odometry_window_s`)"
            );
        }
        if ekf.counters().start_corrections > corrections_before && !quiet {
            tracing::info!(
                data_time_s = t,
                corrections = ekf.counters().start_corrections,
                "the buoy EKF's start did not hold: the grown odometry window's fix disagrees with it, so it \
                 re-started there (`ekf.recovery.confirm_checks`)"
            );
        }
        if ekf.counters().outlier_branch_switches > switches_before && !quiet {
            tracing::warn!(
                data_time_s = t,
                undone = ekf.counters().outlier_branch_switches,
                "the buoy EKF undid a range it had taken as doubtful: the ranges since fit the filter without it \
                 (counted as rejected; `ekf.range.doubtful_sigma`)"
            );
        }
        self.waiting += waiting;
        self.range_nis.0 += nis_taken.0;
        self.range_nis.1 += nis_taken.1;
        if reason.is_some() {
            self.waiting_reason = reason;
            self.waiting_since_s.get_or_insert(t);
        }
        if estimate.is_none()
            && !quiet
            && let Some(reason) = &self.waiting_reason
            && self.waiting_since_s.is_some_and(|t0| t - t0 >= WAIT_WARN_AFTER_S)
            && self.waiting_warned.is_none_or(|w| w.elapsed() >= WAIT_WARN_EVERY)
        {
            self.waiting_warned = Some(Instant::now());
            tracing::warn!(
                ranges_waiting = self.waiting,
                data_time_s = t,
                min_buoys = self.settings.ekf.init.min_buoys,
                "the buoy EKF is not initialised yet, no fix published: {reason} (settings `ekf.init`)"
            );
        }
        for e in errors {
            Self::count(&mut self.filter_errors, e);
        }
        match estimate? {
            Ok(estimate) => {
                self.trajectory.push(TrajectorySample::of(t, &estimate));
                let cross_prev = self.last_fix_ns.zip(cross);
                self.last_fix_ns = Some(r.stamp_ns);
                Some(Fix { stamp_ns: r.stamp_ns, origin_ns: r.origin_ns, estimate, used, rejected, cross_prev })
            }
            Err(e) => {
                Self::count(&mut self.filter_errors, format!("estimate: {e}"));
                None
            }
        }
    }
}

/// `world_from_body` of a fix for the TUM file: the position, and the heading as a yaw when known.
pub fn fix_pose(position: &Vector3<f64>, heading_rad: Option<f64>) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::from(*position),
        UnitQuaternion::from_euler_angles(0.0, 0.0, heading_rad.unwrap_or(0.0)),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use buoy::BuoyEntry;
    use geometry::trajectory::dead_reckoning;

    fn settings() -> BuoyEkfSettings {
        let mut s = BuoyEkfSettings::default();
        s.ekf.mode = Mode::Planar;
        s.ekf.buoys = [[0.0, 0.0], [40.0, 0.0], [40.0, 40.0], [0.0, 40.0]]
            .iter()
            .enumerate()
            .map(|(i, p)| BuoyEntry { id: i as u32, position_m: [p[0], p[1], 0.0] })
            .collect();
        s
    }

    fn ranges_at(p: Vector3<f64>, s: &BuoyEkfSettings) -> Vec<BuoyRange> {
        s.ekf
            .buoys
            .iter()
            .map(|b| BuoyRange {
                buoy_id: b.id,
                _reserved: 0,
                range_m: (Vector3::from(b.position_m) - p).norm(),
                sigma_m: 0.1,
            })
            .collect()
    }

    fn odo(v: f64) -> OdometryInput {
        let mut c = [0.0; 16];
        c[0] = 0.01;
        c[15] = 1e-6;
        OdometryInput { v_mps: v, delta_theta_rad: [0.0; 3], dt_s: 0.1, input_covariance: c }
    }

    #[test]
    fn ranges_wait_for_odometry_up_to_their_stamp_and_are_applied_in_stamp_order() {
        let s = settings();
        let mut st = BuoyState::new(s.clone());
        let now = Instant::now();
        let p = Vector3::new(10.0, 12.0, 0.0);
        st.push_ranges(1_000_000_000, 0, &ranges_at(p, &s), now);
        assert!(st.step(false, now).is_empty(), "no odometry up to 1 s yet: the ranges wait");
        assert_eq!(st.pending(), 1);
        for k in 1..=10u64 {
            st.push_odometry(k * 100_000_000, &odo(0.0));
        }
        let fixes = st.step(false, now);
        assert_eq!(fixes.len(), 1, "odometry reached the stamp");
        assert_eq!(st.inputs.len(), 10);
        assert!((fixes[0].estimate.position_m - p).norm() < 0.5, "{}", fixes[0].estimate.position_m);
        // A ranges message with no odometry behind it goes once other inputs are odometry_wait_s
        // (data time) past it ...
        st.push_ranges(2_000_000_000, 0, &ranges_at(p, &s), now);
        assert!(st.step(false, now + Duration::from_secs(1)).is_empty(), "wall time alone does not release it");
        st.push_ranges(2_400_000_000, 0, &ranges_at(p, &s), now);
        assert!(st.step(false, now).is_empty(), "0.4 s of data time is not enough");
        st.push_ranges(2_500_000_000, 0, &ranges_at(p, &s), now);
        // Not in the round that received the later ranges: odometry published before them may
        // have been published after the odometry was received (a fast replay); the next round
        // has received it.
        assert!(st.step(false, now).is_empty(), "the round that received the evidence waits");
        assert_eq!(st.step(false, now).len(), 1, "0.5 s of data time past the first ranges");
        // ... or once it has waited odometry_stall_s of wall time (every input stalled).
        assert_eq!(st.next_deadline(), Some(now + Duration::from_secs(5)));
        assert!(st.step(false, now + Duration::from_secs(4)).is_empty());
        assert_eq!(st.step(false, now + Duration::from_secs(5)).len(), 2);
    }

    #[test]
    fn bad_messages_are_counted_and_lose_nothing_else() {
        let s = settings();
        let mut st = BuoyState::new(s.clone());
        let now = Instant::now();
        let p = Vector3::new(10.0, 12.0, 0.0);
        let mut bad = odo(0.0);
        bad.v_mps = f64::NAN;
        st.push_odometry(100_000_000, &bad);
        st.push_odometry(200_000_000, &odo(0.0));
        let mut rs = ranges_at(p, &s);
        rs.push(BuoyRange { buoy_id: 77, _reserved: 0, range_m: 5.0, sigma_m: 0.1 });
        rs.push(BuoyRange { buoy_id: 1, _reserved: 0, range_m: f64::NAN, sigma_m: 0.1 });
        st.push_ranges(200_000_000, 0, &rs, now);
        let fixes = st.step(true, now);
        assert_eq!(fixes.len(), 1);
        assert_eq!(fixes[0].rejected, 2, "unknown buoy and NaN range");
        assert_eq!(st.invalid.values().sum::<u64>(), 1, "{:?}", st.invalid);
        assert_eq!(st.filter_errors.values().sum::<u64>(), 2, "{:?}", st.filter_errors);
    }

    #[test]
    fn dead_reckoning_integrates_the_process_model() {
        let inputs: Vec<_> = (1..=10)
            .map(|k| {
                (k as f64 * 0.1, ProcessInput { v_mps: 1.0, delta_theta_rad: Vector3::new(0.0, 0.0, 0.0), dt_s: 0.1 })
            })
            .collect();
        let start = fix_pose(&Vector3::new(5.0, 0.0, 0.0), Some(std::f64::consts::FRAC_PI_2));
        let dr = dead_reckoning(&start, &inputs);
        let end = dr.last().unwrap().1.translation.vector;
        assert!((end - Vector3::new(5.0, 1.0, 0.0)).norm() < 1e-9, "{end}");
    }
}
