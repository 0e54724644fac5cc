//! Fusion's part of summary.json (`fusion`, `pipeline_latency_ms` of the fused poses, and the
//! fused estimates' `ate_m` when a ground truth is there), described in docs/summary.schema.json.

use std::collections::BTreeMap;

use pipeline_runtime::summary::{CountedPercentiles, PositionNees};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::SourceCounts;

/// What the `fusion` stage adds to summary.json.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct FusionPart {
    /// The fusion's run.
    pub fusion: FusionSummary,
    /// Latency from a stereo frame to its fused pose.
    pub pipeline_latency_ms: FusedLatency,
    /// Accuracy against the ground truth (when the source wrote one).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ate_m: Option<FusedAte>,
    /// The covariances' consistency against the ground truth (when the source wrote one).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nees: Option<FusedNees>,
}

/// `nees` (fusion's keys): the mean position NEES of the fused poses against the ground truth,
/// their position covariance being the upper-left 3×3 block of the published 6×6 (world frame).
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct FusedNees {
    /// The final fused path (`fused_global.tum`).
    pub fused: Option<PositionNees>,
    /// The fused poses as published live (`fused_live.tum`).
    pub fused_live: Option<PositionNees>,
    /// The buoy positions the synchronizer paired with the SLAM poses (interpolated between
    /// fixes with their cross-covariances, docs/EQUATIONS.md §5.1a), what fusion takes.
    #[serde(default)]
    pub buoy: Option<PositionNees>,
}

/// `fusion`: the fused path, the local maps' alignment, the global map.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct FusionSummary {
    /// Poses in the final, globally consistent path.
    pub poses: usize,
    /// The poses published live, by source.
    pub live: SourceCounts,
    /// The final path's poses, by source.
    #[serde(rename = "final")]
    pub final_: SourceCounts,
    /// Local maps (segments) seen.
    pub segments: usize,
    /// Local maps aligned to the world.
    pub segments_aligned: usize,
    /// Local maps whose transform started from the previous one's, carried over to where they
    /// began (`handover_max_gap_s`).
    pub segments_handed_over: usize,
    /// Of those, the local maps whose fixes disagreed with the carried transform (χ²₆ above
    /// 0.999), aligned with their fixes alone (and local maps whose fixes disagreed with the
    /// compass's level prior).
    pub priors_rejected: usize,
    /// New local maps fusion asked SLAM for.
    pub new_local_maps_requested: u64,
    /// Landmarks in the global map.
    pub global_landmarks: usize,
    /// Global landmarks merged from several local maps.
    pub global_landmarks_merged: usize,
    /// Inputs refused as invalid, by reason.
    pub invalid_inputs: BTreeMap<String, u64>,
    /// Predicted poses published (before their pair proper).
    pub predicted: usize,
    /// The buoy fixes' error autocorrelation by lag in fixes, from the local maps' alignment
    /// residuals (lag 0 first, then while positive): what the final path's covariances account
    /// for (docs/EQUATIONS.md §5.3).
    pub fix_error_autocorrelation: Vec<f64>,
}

/// `pipeline_latency_ms` (fusion's keys), ms.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct FusedLatency {
    /// From the stereo frame's origin to its fused pose (the pair proper) leaving fusion.
    pub stereo_to_fused_pose: CountedPercentiles,
    /// From the stereo frame's origin to the first fused pose of its stamp (a prediction, or the
    /// pair proper) leaving fusion.
    pub stereo_to_first_fused_pose: CountedPercentiles,
}

/// `ate_m` (fusion's keys): RMS position error at the ground truth's stamps (nearest, no
/// alignment), m.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct FusedAte {
    /// The final fused path (`fused_global.tum`).
    pub fused: Option<f64>,
    /// The fused poses as published live.
    pub fused_live: Option<f64>,
    /// The first fused pose of each stamp (a prediction where there was one).
    pub fused_first: Option<f64>,
    /// The predicted poses.
    pub fused_predicted: Option<f64>,
    /// The buoy fixes fusion received.
    pub buoy: Option<f64>,
    /// SLAM's poses mapped to the world by their local map's alignment.
    pub slam_global: Option<f64>,
}
