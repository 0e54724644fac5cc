//! What the buoy EKF takes and gives: odometry inputs, the outcome of a range or a fix, its
//! counters and its estimate.

use nalgebra::{Matrix3, Vector3};

use crate::error::TrilaterationError;

/// An odometry input over the interval (t − `dt_s`, t] (EQUATIONS §1: forward speed and yaw turn).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OdometryInput {
    /// Interval length, s (> 0).
    pub dt_s: f64,
    /// Forward speed along the body x axis, m/s.
    pub v_mps: f64,
    /// Yaw increment over the interval (δθz), rad.
    pub dtheta_rad: f64,
    /// Variance of the speed, m²/s².
    pub var_v: f64,
    /// Variance of the yaw increment, rad².
    pub var_dtheta: f64,
}

/// What happened to a range.
#[derive(Debug, Clone, PartialEq)]
pub enum RangeOutcome {
    /// Used in the update.
    Accepted {
        /// Innovation r − h(x), m.
        innovation_m: f64,
        /// Normalised innovation ν²/S.
        nis: f64,
        /// Huber weight applied (1: full weight).
        weight: f64,
    },
    /// Rejected by the gate (and counted).
    Rejected {
        /// Innovation r − h(x), m.
        innovation_m: f64,
        /// Normalised innovation ν²/S.
        nis: f64,
        /// This rejection triggered a recovery (see the module docs).
        recovery: bool,
    },
    /// Buffered for initialisation, which is not possible yet for this reason.
    Waiting(TrilaterationError),
    /// This range completed the initialisation.
    Initialised,
}

/// What happened to a depth reading or a position fix.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FixOutcome {
    /// Used in the update, with its normalised innovation.
    Accepted {
        /// Normalised innovation νᵀS⁻¹ν.
        nis: f64,
    },
    /// Rejected by the gate.
    Rejected {
        /// Normalised innovation νᵀS⁻¹ν.
        nis: f64,
    },
    /// Rejected too often in a row: the position was reset to the fix.
    Reset,
    /// Kept for initialisation (a depth reading before the first trilateration).
    Stored,
    /// This fix initialised the filter.
    Initialised,
}

/// Range counters of one buoy.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BuoyCounters {
    /// Buoy id.
    pub id: u32,
    /// Ranges accepted.
    pub accepted: u64,
    /// Ranges rejected by the gate, or taken and undone (`outlier_branch_switches`).
    pub rejected: u64,
    /// Ranges rejected in a row (reset by an accepted one).
    pub consecutive_rejected: u32,
}

/// Counters of the filter's decisions.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Counters {
    /// Ranges accepted.
    pub accepted: u64,
    /// Ranges rejected by the gate, or taken and undone (`outlier_branch_switches`).
    pub rejected: u64,
    /// Ranges rejected in a row, any buoy (reset by an accepted one).
    pub consecutive_rejected: u32,
    /// Recoveries (covariance inflations after rejections in a row).
    pub recoveries: u64,
    /// Re-starts of a lost filter from a robust window fix (see `recovery.check_rejected_share`).
    pub reinitialisations: u64,
    /// Doubtful ranges (taken at more than `range.doubtful_sigma`) that the ranges after them showed to be wrong:
    /// the filter went on from the branch that left them out.
    pub outlier_branch_switches: u64,
    /// Lost-filter checks whose window gave no fix (the filter went on as it was).
    pub lost_checks_without_fix: u64,
    /// Starts from a window fix that a later fix of the grown window disagreed with: the
    /// filter re-started there (see `recovery.confirm_checks`).
    pub start_corrections: u64,
    /// Checks of a start against the grown window (see `recovery.confirm_checks`), with a fix.
    pub start_checks: u64,
    /// Accepted ranges from which the range scale and bias states did not learn (normalised
    /// innovation beyond `range.calibration_k`).
    pub calibration_held: u64,
    /// Accepted ranges from which at least one range scale or bias state did not learn because
    /// the recent ranges do not determine it (`range.observable_sigma_fraction`).
    pub calibration_unobservable: u64,
    /// Bias states reset to their prior.
    pub bias_resets: u64,
    /// Depth readings rejected.
    pub depth_rejected: u64,
    /// Position fixes rejected.
    pub fixes_rejected: u64,
    /// Per buoy, in buoy-table order.
    pub per_buoy: Vec<BuoyCounters>,
}

impl Counters {
    /// The counters of buoy `id`.
    pub fn buoy(&self, id: u32) -> Option<&BuoyCounters> {
        self.per_buoy.iter().find(|b| b.id == id)
    }
}

/// A range bias estimate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BiasEstimate {
    /// Buoy id.
    pub buoy_id: u32,
    /// Bias, m (the global bias in `global` mode).
    pub bias_m: f64,
    /// Its σ, m.
    pub sigma_m: f64,
}

/// The filter's estimate at its current time.
#[derive(Debug, Clone, PartialEq)]
pub struct Estimate {
    /// Time, s.
    pub t_s: f64,
    /// Position in the world frame, m (planar mode: z = `planar_height_m`).
    pub position_m: Vector3<f64>,
    /// Covariance of the position, m² (planar mode: the z row and column are 0).
    pub covariance_m2: Matrix3<f64>,
    /// Velocity in the world frame, m/s (planar mode: z = 0).
    pub velocity_mps: Vector3<f64>,
    /// Covariance of the velocity, m²/s².
    pub velocity_covariance: Matrix3<f64>,
    /// Heading, rad; `None` while unknown (no prior, hypotheses not merged yet).
    pub heading_rad: Option<f64>,
    /// σ of the heading (of the hypothesis mixture while unknown), rad.
    pub heading_sigma_rad: f64,
    /// Range scale factor s and its σ, when estimated.
    pub range_scale: Option<(f64, f64)>,
    /// Turn-rate bias and its σ, rad/s, when estimated.
    pub turn_bias_rps: Option<(f64, f64)>,
    /// Range biases per buoy (empty without bias states).
    pub biases: Vec<BiasEstimate>,
    /// Heading hypotheses alive (1 once merged).
    pub hypotheses: usize,
}
