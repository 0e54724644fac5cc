//! The buoy EKF's part of summary.json (`buoy_ekf`, and `ate_m.buoy_ekf`,
//! `ate_m.dead_reckoning` and `nees.buoy_ekf` when a ground truth is there), described in
//! docs/summary.schema.json.

use std::collections::BTreeMap;

use pipeline_runtime::summary::PositionNees;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// What the `buoy_ekf` stage adds to summary.json.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct BuoyEkfPart {
    /// The filter's run.
    pub buoy_ekf: BuoyEkfSummary,
    /// Accuracy against the ground truth (when the source wrote one).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ate_m: Option<BuoyAte>,
    /// Consistency of the covariance against the ground truth (when the source wrote one).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nees: Option<BuoyNeesPart>,
}

/// `nees`: what the buoy EKF adds to it.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct BuoyNeesPart {
    /// The position's NEES over the filter's estimates.
    pub buoy_ekf: PositionNees,
}

/// `buoy_ekf.range_nis`: the mean normalised innovation squared ν²/S of the ranges the filter
/// took (χ²₁ each when the filter is consistent: mean 1), with Bar-Shalom's 95 % interval for
/// that mean (docs/EQUATIONS.md §8a). The gate (`range.gate_probability`) leaves out the largest
/// innovations, which lowers a consistent filter's mean by about 1 − p of the gate's probability
/// mass beyond it (under 0.01 at 0.999).
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct RangeNis {
    /// Mean ν²/S over the ranges taken.
    pub mean: Option<f64>,
    /// Ranges scored.
    pub samples: u64,
    /// The 95 % interval of the mean for a consistent filter, [low, high].
    pub interval_95: [f64; 2],
    /// Whether the mean lies in it (below: the innovations' covariance is too large; above: too
    /// small).
    pub consistent: bool,
}

/// `buoy_ekf`: fixes, ranges taken and refused, calibration.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct BuoyEkfSummary {
    /// Fixes published.
    pub fixes: u64,
    /// Poses in `buoy_ekf.tum` (one per odometry step once initialised).
    pub trajectory_samples: usize,
    /// Ranges the filter took.
    pub ranges_accepted: u64,
    /// The NIS test of the ranges taken (none taken: absent).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub range_nis: Option<RangeNis>,
    /// Ranges refused by the gate, or taken and undone.
    pub ranges_rejected: u64,
    /// Recoveries after a run of refused ranges.
    pub recoveries: u64,
    /// Restarts of the filter from a new window fix.
    pub reinitialisations: u64,
    /// Times the copy that left a doubtful range out won.
    pub outlier_branch_switches: u64,
    /// Lost-track checks that found no fix.
    pub lost_checks_without_fix: u64,
    /// Checks of the start against later ranges.
    pub start_checks: u64,
    /// Starts those checks corrected.
    pub start_corrections: u64,
    /// Range biases reset.
    pub bias_resets: u64,
    /// Ranges the calibration states did not learn from (too large for the position).
    pub calibration_held: u64,
    /// Ranges the calibration states did not learn from (not determined by the ranges).
    pub calibration_unobservable: u64,
    /// Share of refused ranges among the last ones (`null` before any).
    pub rejected_share_at_end: Option<RejectedShare>,
    /// Depth readings refused.
    pub depth_rejected: u64,
    /// Ranges that came before the filter started.
    pub ranges_waiting_for_initialisation: u64,
    /// Whether the filter ever started.
    pub initialised: bool,
    /// Why it was waiting, the last time it was (`null` when it never waited).
    pub last_waiting_reason: Option<String>,
    /// Each buoy's ranges.
    pub per_buoy: Vec<PerBuoy>,
    /// The range biases at the end, by buoy (`null` when the filter never started).
    pub range_biases_m: Option<Vec<RangeBias>>,
    /// The range scale factor at the end (`null` without the state).
    pub range_scale: Option<f64>,
    /// Inputs refused as invalid, by reason.
    pub invalid_inputs: BTreeMap<String, u64>,
    /// The filter's numerical failures, by kind.
    pub filter_errors: BTreeMap<String, u64>,
}

/// `buoy_ekf.rejected_share_at_end`.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct RejectedShare {
    /// Share refused, 0-1.
    pub share: f64,
    /// Of how many of the last ranges.
    pub of_last_ranges: usize,
}

/// One buoy's ranges.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct PerBuoy {
    /// Buoy id.
    pub id: u32,
    /// Ranges taken.
    pub accepted: u64,
    /// Ranges refused.
    pub rejected: u64,
    /// rejected / (accepted + rejected).
    pub rejected_share: f64,
}

/// One buoy's range bias.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct RangeBias {
    /// Buoy id.
    pub buoy_id: u32,
    /// Bias, m.
    pub bias_m: f64,
    /// Its standard deviation, m.
    pub sigma_m: f64,
}

/// `ate_m.buoy_ekf` and `ate_m.dead_reckoning`.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct BuoyAte {
    /// RMS position error of the EKF's fixes at the ground truth's stamps (nearest), m.
    pub buoy_ekf: Option<f64>,
    /// RMS position error of the odometry integrated from the true start, m (with odometry).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dead_reckoning: Option<f64>,
}
