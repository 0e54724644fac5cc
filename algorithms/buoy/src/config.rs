//! The estimator's settings ([`BuoyConfig`]), with defaults and a validation pass that names
//! each bad key (keys are relative to the config table, e.g. `range.gate_probability`).
//!
//! Every default is a physical or statistical choice, not a fit to one data set: a 99.9 %
//! innovation gate, Huber's 95 %-efficiency constant, 5 % range scale uncertainty (sound speed
//! or radio clock rate), 2 % wheel slip, and so on. The sensor noise itself (σ of each range, of
//! the odometry speed and turn) comes with each measurement, not from here.

use serde::{Deserialize, Serialize};
use validation::{Issues, Validate};

/// Geometry of the estimate.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Mode {
    /// 3-D: position (x, y, z); ranges are slant ranges; depth readings constrain z.
    #[default]
    Spatial,
    /// 2-D, for ground vehicles: position (x, y) with z fixed at [`BuoyConfig::planar_height_m`].
    /// A range is the slant range sqrt(horizontal² + Δz²) with the known height difference
    /// Δz = buoy z − `planar_height_m` (0 when the buoys are given at the vehicle's height,
    /// which makes the ranges planar).
    Planar,
}

/// Which range biases the filter estimates as states.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum BiasMode {
    /// None: ranges are unbiased apart from the scale (if estimated).
    None,
    /// One constant bias shared by all buoys (with the scale: an affine range calibration).
    #[default]
    Global,
    /// One constant bias per buoy (transponder delay calibration). With few buoys this leaves
    /// the position of a vehicle that has not moved yet poorly determined.
    PerBuoy,
}

/// How the filter gets its first state.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum InitMethod {
    /// Least-squares trilateration of the first ranges (a position fix, if one comes first,
    /// initialises too); the heading follows from the ranges once the vehicle moves (see
    /// [`InitConfig::heading_hypotheses`]).
    #[default]
    Trilateration,
    /// From `init.prior_position_m` (and `init.prior_heading_rad` when given) at construction.
    Prior,
}

/// A buoy at a known position.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BuoyEntry {
    /// Id, as carried by each range.
    pub id: u32,
    /// Position (x, y, z) in the world frame, m.
    pub position_m: [f64; 3],
}

/// Range measurement model and robustness.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RangeConfig {
    /// Probability of the χ²₁ innovation gate: a range whose normalised innovation ν²/S
    /// exceeds the χ²₁ quantile of this probability is rejected (0.999: ν²/S > 10.83).
    pub gate_probability: f64,
    /// Huber constant on the normalised innovation |ν|/√S: an accepted range beyond it is
    /// down-weighted (its variance scaled by |ν|/(k√S)); 0 turns the down-weighting off.
    pub huber_k: f64,
    /// The range scale and bias states do not learn from a range whose innovation exceeds this
    /// many σ of what they cannot explain themselves (ν² > k²·(H_p P_pp H_pᵀ + R): the position's
    /// uncertainty and the range's noise, not the calibration's own prior). Such a range still
    /// updates the rest of the state (down-weighted by Huber, gated by the full innovation
    /// covariance). Without this a gross error soon after the start, while the bias prior is
    /// still wide (1 m), passes the gate and teaches the bias a metre; with it, calibration is
    /// learned from ranges that agree with the position and only drifts as the evidence builds
    /// up. A gross error does not repeat, a calibration error does: when the previous range to
    /// the same buoy (within 5 s) was held too and the two innovations agree within k·√2 range
    /// σ, the second one teaches the calibration (else a scale learned wrong from a near buoy
    /// right after a start would be locked in by the far buoys' large innovations). 0 turns it
    /// off.
    pub calibration_k: f64,
    /// A range accepted at more than this many σ (normalised innovation |ν|/√S) is doubtful:
    /// the filter takes it (down-weighted by Huber) and runs on alongside a copy that left it
    /// out, both fed the same inputs and ranges; when the ranges after it make the copy 19 times
    /// as likely (the likelihood of each range under each branch, truncated at the gate), the
    /// filter goes on from the copy (`outlier_branch_switches` counts it), else after 12 ranges
    /// or at 19:1 the other way the copy is dropped. One copy at a time. A gross error of 1-2 m
    /// that lands at 2.5-3σ while the filter is itself half a metre off is what it is for: taken,
    /// it turns the heading and the position drifts a metre over the next seconds. 0 turns it
    /// off.
    pub doubtful_sigma: f64,
    /// The range scale and bias states are learned only while the accepted ranges of the last
    /// `observability_window_s` determine them: with the estimated path over that window taken
    /// as right up to a common offset, a state whose σ from those ranges alone (no prior; the
    /// other calibration states and the offset free) exceeds this many times its prior σ is
    /// held (a Schmidt update, counted as `calibration_unobservable`). E.g. 3 buoys seen from
    /// one place cannot tell a global bias from a scale and the position; per-buoy biases need
    /// the vehicle to move. The default 5 (the ranges give at least 1/25 of the prior's
    /// information) holds what the geometry leaves open, as in those examples; stricter values
    /// (1-2) also held the calibration in the first seconds of the indoor UWB data set's short
    /// run and cost it 0.002-0.02 m of ATE (docs/buoy_ekf.md). 0 turns the check off.
    pub observable_sigma_fraction: f64,
    /// The window of accepted ranges for `observable_sigma_fraction`, s.
    pub observability_window_s: f64,
    /// Bias states.
    pub bias: BiasMode,
    /// Prior σ of each bias state, m.
    pub bias_prior_sigma_m: f64,
    /// Random walk of each bias state, m/√s (0: constant).
    pub bias_random_walk_m_per_sqrt_s: f64,
    /// Estimate a range scale factor s common to all buoys, r = (1 + s)·distance + bias
    /// (sound-speed error of acoustic ranges, clock-rate error of radio ranges).
    pub estimate_scale: bool,
    /// Prior σ of s (dimensionless).
    pub scale_prior_sigma: f64,
}

impl Default for RangeConfig {
    fn default() -> Self {
        Self {
            gate_probability: 0.999,
            huber_k: 1.345,
            calibration_k: 3.0,
            doubtful_sigma: 2.0,
            observable_sigma_fraction: 5.0,
            observability_window_s: 30.0,
            bias: BiasMode::Global,
            bias_prior_sigma_m: 1.0,
            bias_random_walk_m_per_sqrt_s: 0.0,
            estimate_scale: true,
            scale_prior_sigma: 0.05,
        }
    }
}

/// Process noise.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MotionConfig {
    /// Constant-velocity model (no odometry; and the vertical axis in spatial mode): σ of the
    /// white-noise acceleration, m/s².
    pub accel_sigma_mps2: f64,
    /// Constant-velocity model: σ of the turn rate, rad/s (the heading variance grows by
    /// (σ·Δt)² while no odometry turns it).
    pub cv_turn_rate_sigma_rps: f64,
    /// Odometry: wheel slip as a fraction of the distance travelled (σ of the position noise
    /// added per step on each horizontal axis is this × |v|·Δt).
    pub slip_fraction: f64,
    /// Odometry: heading random walk on top of the input's own variance, rad/√s.
    pub heading_random_walk_rad_per_sqrt_s: f64,
    /// Estimate a constant bias of the odometry turn rate (gyro bias), rad/s.
    pub estimate_turn_bias: bool,
    /// Prior σ of the turn-rate bias, rad/s.
    pub turn_bias_prior_sigma_rps: f64,
    /// Random walk of the turn-rate bias, rad/s/√s.
    pub turn_bias_random_walk_rps_per_sqrt_s: f64,
    /// A prediction between odometry inputs (to a range's stamp) holds the last input's speed
    /// and turn rate for up to this long after it ended; beyond, the constant-velocity model, s.
    pub input_hold_s: f64,
    /// Odometry from a vehicle that pitches and rolls: the rotation increments are integrated
    /// into an attitude whose roll and pitch relax to level with this time constant, s, and the
    /// world yaw increment and the horizontal speed are taken from it
    /// ([`crate::attitude::LevelledAttitude`]; docs/EQUATIONS.md §5.0). 0 takes the body's z
    /// increment as the yaw increment and the speed as horizontal (a vehicle that stays level).
    pub level_time_constant_s: f64,
}

impl Default for MotionConfig {
    fn default() -> Self {
        Self {
            accel_sigma_mps2: 0.5,
            cv_turn_rate_sigma_rps: 0.2,
            slip_fraction: 0.02,
            heading_random_walk_rad_per_sqrt_s: 0.005,
            estimate_turn_bias: true,
            turn_bias_prior_sigma_rps: 0.01,
            turn_bias_random_walk_rps_per_sqrt_s: 1e-4,
            input_hold_s: 1.0,
            level_time_constant_s: 20.0,
        }
    }
}

/// Initialisation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct InitConfig {
    /// Trilateration or prior.
    pub method: InitMethod,
    /// Trilateration uses the ranges of the last `window_s` seconds (the vehicle should move
    /// less than a range σ in it), s.
    pub window_s: f64,
    /// Distinct buoys a trilateration needs (at least 3; spatial mode needs 4 unless a depth
    /// reading constrains z). The default, 4, is one more than the planar minimum, so that one
    /// wrong range shows in the residual instead of bending an exact fit.
    pub min_buoys: usize,
    /// Largest condition number of the Gauss-Newton normal matrix that is accepted.
    pub max_condition: f64,
    /// Largest normalised RMS residual (|r − d|/σ over the inliers) of an accepted solution.
    pub max_normalised_rms: f64,
    /// Prior position (x, y, z), m (method `prior`).
    pub prior_position_m: [f64; 3],
    /// σ of the prior position on each axis, m.
    pub prior_position_sigma_m: f64,
    /// Prior heading, rad (method `prior`); absent: the heading follows from the ranges.
    pub prior_heading_rad: Option<f64>,
    /// σ of the prior heading, rad.
    pub prior_heading_sigma_rad: f64,
    /// σ of the initial speed on each axis, m/s.
    pub initial_speed_sigma_mps: f64,
    /// Unknown heading with odometry: the filter splits into this many heading hypotheses
    /// (a Gaussian sum, evenly spaced, σ = π/n each) weighted by the ranges' likelihoods.
    pub heading_hypotheses: usize,
    /// The hypotheses merge into one filter once the mixture's heading σ is below this, rad.
    pub heading_max_sigma_rad: f64,
    /// Planar mode with odometry: start (and re-start a lost filter) from a robust fix over a
    /// window of ranges with the positions propagated by odometry (`crate::window_fix`: outliers
    /// found by sampling, heading solved with the position once the path shows it) instead of
    /// the stationary trilateration, which assumes the vehicle stands still and, with exactly 3
    /// buoys, cannot see a wrong range.
    pub odometry_window: bool,
    /// Length of that window, s.
    pub odometry_window_s: f64,
    /// At most this many of the newest ranges in the window.
    pub odometry_window_max_ranges: usize,
    /// Ranges the robust fix must explain (inliers), at least.
    pub odometry_window_min_inliers: usize,
    /// Share of the window's ranges the robust fix must explain.
    pub odometry_window_min_inlier_fraction: f64,
    /// Odometry error per metre of path assumed by the robust fix (added to a range's σ for each
    /// metre between it and the newest range).
    pub odometry_drift_fraction: f64,
    /// The window's fix is ambiguous (the filter waits) while a distinct pose (> 1 m or 30°
    /// from the best) explains the window within this many outliers' worth of truncated cost
    /// (9 χ² units each, an inlier threshold of 3σ). 1: the best must be e^4.5 ≈ 90 times as
    /// likely as any rival. On the heavy-outlier pipeline mission 1 rather than 2 starts
    /// 1-2 s sooner where the rival is only the heading a short path leaves open (mean ATE
    /// 0.424 against 0.440 m, 0.361 against 0.370 m without the outliers); 0 starts on mirror
    /// solutions (a clean run 0.88 m).
    pub odometry_window_ambiguity_margin: f64,
}

impl Default for InitConfig {
    fn default() -> Self {
        Self {
            method: InitMethod::Trilateration,
            window_s: 5.0,
            min_buoys: 4,
            max_condition: 1e8,
            max_normalised_rms: 3.0,
            prior_position_m: [0.0; 3],
            prior_position_sigma_m: 10.0,
            prior_heading_rad: None,
            prior_heading_sigma_rad: 0.1,
            initial_speed_sigma_mps: 1.0,
            heading_hypotheses: 16,
            heading_max_sigma_rad: 0.1,
            odometry_window: true,
            odometry_window_s: 30.0,
            odometry_window_max_ranges: 60,
            odometry_window_min_inliers: 8,
            odometry_window_min_inlier_fraction: 0.6,
            odometry_drift_fraction: 0.05,
            odometry_window_ambiguity_margin: 1.0,
        }
    }
}

/// Recovery from a filter that the gate has locked out.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RecoveryConfig {
    /// After this many ranges in a row rejected (any buoys, none accepted in between) the
    /// filter counts as lost: its position covariance grows by the mean squared innovation of
    /// the run, and its heading variance by `heading_sigma_rad`², so the next ranges pass.
    pub consecutive_rejections: u32,
    /// Heading σ added on a recovery, rad.
    pub heading_sigma_rad: f64,
    /// After this many ranges of one buoy in a row rejected while other buoys' ranges pass,
    /// that buoy's bias state is reset to its prior (per-buoy biases only).
    pub buoy_consecutive_rejections: u32,
    /// After this many position fixes in a row rejected, the position is reset to the fix.
    pub fix_rejections: u32,
    /// Lost-filter check (with the odometry window, `init.odometry_window`): over the last
    /// this many ranges, …
    pub check_ranges: usize,
    /// … a rejected share at or above this (or a recovery) makes the filter ask the window for
    /// a robust fix; a fix that disagrees with the filter (χ²₂ gate of the position difference)
    /// re-starts it there (counted as `reinitialisations`).
    pub check_rejected_share: f64,
    /// A start from the odometry window's fix is provisional: the first fix comes from the
    /// fewest ranges and the shortest path that allow one, and with 3 buoys a range bias the
    /// fix does not model can pull it metres off while the filter, starting there, takes its
    /// calibration states along and accepts what follows. Every `confirm_every_ranges` ranges
    /// after a start the window (grown since) is solved again and compared with the filter
    /// (χ²₂ gate of the position difference); when neither its fix of the raw ranges nor that
    /// of the ranges corrected by the filter's calibration agrees, the filter re-starts at the
    /// first with the calibration at its prior (counted as `start_corrections`). The start holds
    /// once this many checks in a row agree. 0: no checks.
    pub confirm_checks: u32,
    /// Ranges between those checks.
    pub confirm_every_ranges: u32,
}

impl Default for RecoveryConfig {
    fn default() -> Self {
        Self {
            consecutive_rejections: 8,
            heading_sigma_rad: 0.3,
            buoy_consecutive_rejections: 15,
            fix_rejections: 2,
            check_ranges: 20,
            check_rejected_share: 0.4,
            confirm_checks: 3,
            confirm_every_ranges: 5,
        }
    }
}

/// The buoy estimator's settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BuoyConfig {
    /// 2-D or 3-D.
    pub mode: Mode,
    /// Planar mode: the vehicle's (fixed) z, m.
    pub planar_height_m: f64,
    /// The buoy table.
    pub buoys: Vec<BuoyEntry>,
    /// Range model.
    pub range: RangeConfig,
    /// Process noise.
    pub motion: MotionConfig,
    /// Initialisation.
    pub init: InitConfig,
    /// Recovery.
    pub recovery: RecoveryConfig,
}

impl Default for BuoyConfig {
    fn default() -> Self {
        Self {
            mode: Mode::Spatial,
            planar_height_m: 0.0,
            buoys: Vec::new(),
            range: RangeConfig::default(),
            motion: MotionConfig::default(),
            init: InitConfig::default(),
            recovery: RecoveryConfig::default(),
        }
    }
}

impl BuoyConfig {
    /// Spatial mode: the buoys lie in one plane (e.g. all at the surface), so a 3-D fix has a
    /// mirror image across that plane and needs depth readings to pick the side.
    pub fn needs_depth(&self) -> bool {
        let p: Vec<nalgebra::Vector3<f64>> = self.buoys.iter().map(|b| nalgebra::Vector3::from(b.position_m)).collect();
        self.mode == Mode::Spatial
            && (p.len() < 4 || crate::trilaterate::spread_ratio(&p) < crate::trilaterate::DEGENERATE_SPREAD)
    }
}

impl Validate for BuoyConfig {
    fn validate(&self, issues: &mut Issues) {
        let pos = |x: f64| x.is_finite() && x > 0.0;
        let nonneg = |x: f64| x.is_finite() && x >= 0.0;
        issues.check(self.planar_height_m.is_finite(), "planar_height_m", "must be finite");
        issues.check(self.buoys.len() >= 3, "buoys", "needs at least 3 buoys");
        for (i, b) in self.buoys.iter().enumerate() {
            issues.check(
                b.position_m.iter().all(|c| c.is_finite()),
                format!("buoys[{i}].position_m"),
                "must be finite",
            );
            if self.buoys[..i].iter().any(|o| o.id == b.id) {
                issues.check(false, format!("buoys[{i}].id"), format!("buoy id {} is listed twice", b.id));
            }
        }
        if self.buoys.len() >= 3 && self.buoys.iter().all(|b| b.position_m.iter().all(|c| c.is_finite())) {
            let xy: Vec<nalgebra::Vector2<f64>> =
                self.buoys.iter().map(|b| nalgebra::Vector2::new(b.position_m[0], b.position_m[1])).collect();
            let msg = format!(
                "all {} buoys lie on one line seen from above: every position has a mirror image across it that \
                 reads the same ranges; add a buoy off the line",
                self.buoys.len()
            );
            issues.check(crate::trilaterate::spread_ratio(&xy) >= crate::trilaterate::DEGENERATE_SPREAD, "buoys", &msg);
        }
        let r = &self.range;
        issues.check(
            r.gate_probability > 0.0 && r.gate_probability < 1.0,
            "range.gate_probability",
            "must be in (0, 1)",
        );
        issues.check(
            r.huber_k == 0.0 || (pos(r.huber_k) && r.huber_k >= 1.0),
            "range.huber_k",
            "must be 0 (off) or >= 1",
        );
        issues.check(
            r.doubtful_sigma == 0.0 || (pos(r.doubtful_sigma) && r.doubtful_sigma >= 1.0),
            "range.doubtful_sigma",
            "must be 0 (off) or >= 1",
        );
        issues.check(
            r.calibration_k == 0.0 || (pos(r.calibration_k) && r.calibration_k >= 1.0),
            "range.calibration_k",
            "must be 0 (off) or >= 1",
        );
        issues.check(
            r.observable_sigma_fraction.is_finite() && r.observable_sigma_fraction >= 0.0,
            "range.observable_sigma_fraction",
            "must be >= 0 (0: off)",
        );
        issues.check(pos(r.observability_window_s), "range.observability_window_s", "must be positive and finite");
        issues.check(pos(r.bias_prior_sigma_m), "range.bias_prior_sigma_m", "must be > 0");
        issues.check(nonneg(r.bias_random_walk_m_per_sqrt_s), "range.bias_random_walk_m_per_sqrt_s", "must be >= 0");
        issues.check(
            pos(r.scale_prior_sigma) && r.scale_prior_sigma < 0.5,
            "range.scale_prior_sigma",
            "must be in (0, 0.5)",
        );
        let m = &self.motion;
        issues.check(pos(m.accel_sigma_mps2), "motion.accel_sigma_mps2", "must be > 0");
        issues.check(nonneg(m.cv_turn_rate_sigma_rps), "motion.cv_turn_rate_sigma_rps", "must be >= 0");
        issues.check(nonneg(m.slip_fraction) && m.slip_fraction < 1.0, "motion.slip_fraction", "must be in [0, 1)");
        issues.check(
            nonneg(m.heading_random_walk_rad_per_sqrt_s),
            "motion.heading_random_walk_rad_per_sqrt_s",
            "must be >= 0",
        );
        issues.check(pos(m.turn_bias_prior_sigma_rps), "motion.turn_bias_prior_sigma_rps", "must be > 0");
        issues.check(
            nonneg(m.turn_bias_random_walk_rps_per_sqrt_s),
            "motion.turn_bias_random_walk_rps_per_sqrt_s",
            "must be >= 0",
        );
        issues.check(nonneg(m.input_hold_s), "motion.input_hold_s", "must be >= 0");
        issues.check(nonneg(m.level_time_constant_s), "motion.level_time_constant_s", "must be >= 0");
        let i = &self.init;
        issues.check(pos(i.window_s), "init.window_s", "must be > 0");
        issues.check(i.min_buoys >= 3, "init.min_buoys", "must be >= 3");
        // A filter that needs more distinct buoys to start than there are would wait forever.
        let starts = self.buoys.len() < 3 || i.min_buoys <= self.buoys.len();
        let msg = format!(
            "is {} but `buoys` lists {}: the filter could never initialise; set it to {} or fewer (>= 3), or add buoys",
            i.min_buoys,
            self.buoys.len(),
            self.buoys.len()
        );
        issues.check(starts, "init.min_buoys", &msg);
        issues.check(pos(i.max_condition) && i.max_condition > 1.0, "init.max_condition", "must be > 1");
        issues.check(pos(i.max_normalised_rms), "init.max_normalised_rms", "must be > 0");
        issues.check(i.prior_position_m.iter().all(|c| c.is_finite()), "init.prior_position_m", "must be finite");
        issues.check(pos(i.prior_position_sigma_m), "init.prior_position_sigma_m", "must be > 0");
        issues.check(i.prior_heading_rad.is_none_or(f64::is_finite), "init.prior_heading_rad", "must be finite");
        issues.check(pos(i.prior_heading_sigma_rad), "init.prior_heading_sigma_rad", "must be > 0");
        issues.check(pos(i.initial_speed_sigma_mps), "init.initial_speed_sigma_mps", "must be > 0");
        issues.check((4..=64).contains(&i.heading_hypotheses), "init.heading_hypotheses", "must be 4..=64");
        issues.check(
            pos(i.heading_max_sigma_rad) && i.heading_max_sigma_rad < 1.0,
            "init.heading_max_sigma_rad",
            "must be in (0, 1)",
        );
        issues.check(pos(i.odometry_window_s), "init.odometry_window_s", "must be > 0");
        issues.check(i.odometry_window_max_ranges >= 8, "init.odometry_window_max_ranges", "must be >= 8");
        issues.check(i.odometry_window_min_inliers >= 4, "init.odometry_window_min_inliers", "must be >= 4");
        issues.check(
            i.odometry_window_min_inliers <= i.odometry_window_max_ranges,
            "init.odometry_window_min_inliers",
            "must be <= init.odometry_window_max_ranges",
        );
        issues.check(
            i.odometry_window_min_inlier_fraction > 0.0 && i.odometry_window_min_inlier_fraction <= 1.0,
            "init.odometry_window_min_inlier_fraction",
            "must be in (0, 1]",
        );
        issues.check(
            nonneg(i.odometry_drift_fraction) && i.odometry_drift_fraction < 1.0,
            "init.odometry_drift_fraction",
            "must be in [0, 1)",
        );
        issues.check(
            nonneg(i.odometry_window_ambiguity_margin),
            "init.odometry_window_ambiguity_margin",
            "must be >= 0 (outliers' worth of cost)",
        );
        let c = &self.recovery;
        issues.check(c.consecutive_rejections >= 1, "recovery.consecutive_rejections", "must be >= 1");
        issues.check(nonneg(c.heading_sigma_rad), "recovery.heading_sigma_rad", "must be >= 0");
        issues.check(c.buoy_consecutive_rejections >= 1, "recovery.buoy_consecutive_rejections", "must be >= 1");
        issues.check(c.fix_rejections >= 1, "recovery.fix_rejections", "must be >= 1");
        issues.check(c.check_ranges >= 4, "recovery.check_ranges", "must be >= 4");
        issues.check(
            c.check_rejected_share > 0.0 && c.check_rejected_share <= 1.0,
            "recovery.check_rejected_share",
            "must be in (0, 1]",
        );
        issues.check(
            c.confirm_checks == 0 || c.confirm_every_ranges >= 1,
            "recovery.confirm_every_ranges",
            "must be >= 1 (or recovery.confirm_checks = 0)",
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn with_buoys() -> BuoyConfig {
        BuoyConfig {
            buoys: (0..4).map(|i| BuoyEntry { id: i, position_m: [i as f64, (i * i) as f64, 0.0] }).collect(),
            ..BuoyConfig::default()
        }
    }

    #[test]
    fn defaults_with_a_buoy_table_are_valid() {
        assert!(with_buoys().issues().is_empty());
        // The default has no buoys: that is the one problem.
        let keys: Vec<String> = BuoyConfig::default().issues().into_iter().map(|i| i.key).collect();
        assert_eq!(keys, ["buoys"]);
    }

    #[test]
    fn more_buoys_to_start_than_configured_is_refused() {
        let mut c = with_buoys();
        c.buoys.pop(); // 3 buoys, min_buoys 4 by default
        let issues = c.issues().into_vec();
        assert_eq!(issues.len(), 1, "{issues:?}");
        assert_eq!(issues[0].key, "init.min_buoys");
        assert!(
            issues[0].message.contains("never initialise") && issues[0].message.contains("lists 3"),
            "{}",
            issues[0].message
        );
        c.init.min_buoys = 3;
        assert!(c.issues().is_empty());
    }

    #[test]
    fn buoys_on_one_line_are_refused_and_coplanar_ones_need_depth_in_3d() {
        let mut c = with_buoys();
        for (i, b) in c.buoys.iter_mut().enumerate() {
            b.position_m = [i as f64 * 10.0, i as f64 * 5.0, -(i as f64)];
        }
        let issues = c.issues().into_vec();
        assert_eq!(issues.len(), 1, "{issues:?}");
        assert!(issues[0].key == "buoys" && issues[0].message.contains("one line"), "{issues:?}");
        let c = with_buoys(); // all at z = 0
        assert!(c.needs_depth());
        let mut c = with_buoys();
        c.buoys[3].position_m[2] = -5.0;
        assert!(!c.needs_depth());
        c.mode = Mode::Planar;
        assert!(!c.needs_depth());
    }

    #[test]
    fn validation_names_the_offending_keys() {
        let mut c = with_buoys();
        c.buoys[2].id = 0;
        c.buoys[1].position_m[2] = f64::NAN;
        c.range.gate_probability = 1.0;
        c.range.huber_k = 0.5;
        c.motion.slip_fraction = -0.1;
        c.init.min_buoys = 2;
        c.init.prior_heading_rad = Some(f64::INFINITY);
        c.recovery.fix_rejections = 0;
        let keys: Vec<String> = c.issues().into_iter().map(|i| i.key).collect();
        assert_eq!(
            keys,
            [
                "buoys[1].position_m",
                "buoys[2].id",
                "range.gate_probability",
                "range.huber_k",
                "motion.slip_fraction",
                "init.min_buoys",
                "init.prior_heading_rad",
                "recovery.fix_rejections"
            ]
        );
    }

    #[test]
    fn toml_with_an_unknown_key_is_refused_and_a_partial_table_gets_defaults() {
        let text = r#"
            mode = "planar"
            buoys = [{ id = 1, position_m = [0.0, 0.0, 0.0] }]
            [range]
            bias = "per_buoy"
        "#;
        let c: BuoyConfig = toml::from_str(text).unwrap();
        assert_eq!(c.mode, Mode::Planar);
        assert_eq!(c.range.bias, BiasMode::PerBuoy);
        assert_eq!(c.range.gate_probability, 0.999);
        let e = toml::from_str::<BuoyConfig>("[range]\ngate = 0.9\n").unwrap_err().to_string();
        assert!(e.contains("unknown field `gate`"), "{e}");
    }
}
