//! FastSLAM's part of summary.json (`slam`, and `ate_m.slam` and `nees` when a ground truth is
//! there), described in docs/summary.schema.json.

use pipeline_runtime::summary::{Percentiles, finite};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::MotionModel;

/// What the `fastslam` stage adds to summary.json.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct FastSlamPart {
    /// The filter's run.
    pub slam: SlamSummary,
    /// Accuracy against the ground truth (when the source wrote one).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ate_m: Option<SlamAte>,
    /// Consistency against the ground truth (when the source wrote one).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nees: Option<SlamNees>,
}

/// `slam`: the particle filter's run.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct SlamSummary {
    /// Particles.
    pub particles: usize,
    /// The proposal (`optimal`: FastSLAM 2.0, `motion`: FastSLAM 1.0).
    pub proposal: String,
    /// Poses estimated (one per stereo frame).
    pub frames: usize,
    /// Local maps (segments) started.
    pub segments: u32,
    /// Wall time of the filter's update per frame, ms.
    pub update_ms: Percentiles,
    /// Stereo observations refused as invalid.
    pub rejected_observations: usize,
    /// Odometry messages refused as invalid.
    pub rejected_odometry: usize,
    /// How the particles are predicted between frames.
    pub motion_model: MotionModel,
    /// Mean normalised innovation squared of the associated observations (expected 3 when the
    /// noise model is right; `null` without associations).
    pub mean_nis: Option<f64>,
    /// Association candidates per observation.
    pub candidates_per_observation: f64,
    /// Track-id matches refused by the gate.
    pub rejected_track_matches: u64,
    /// The stereo front end (`motion_model = "stereo"`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frontend: Option<FrontendSummary>,
    /// Accuracy and consistency per local map (when a ground truth is there).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub per_segment: Option<Vec<SegmentSummary>>,
}

/// `slam.frontend`: the camera-only front end's frame-to-frame motions.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct FrontendSummary {
    /// Frames predicted.
    pub frames: u64,
    /// Motions found by feature track ids.
    pub by_track_ids: u64,
    /// Motions found around the constant-velocity prior.
    pub guided: u64,
    /// Motions found by the prior-free search.
    pub search: u64,
    /// Frames without a motion (predicted by constant velocity instead).
    pub failed: u64,
    /// Inliers per motion found.
    pub mean_inliers: f64,
    /// Wall time of the front end per frame, ms.
    pub mean_ms: f64,
    /// Feature tracks continued after frames that did not see their feature
    /// (`frontend.bridge_gap_frames`).
    pub bridged_tracks: u64,
}

/// One local map's scores against the ground truth.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct SegmentSummary {
    /// Segment (local map) id.
    pub segment: u32,
    /// Poses evaluated.
    pub samples: usize,
    /// RMS position error after the best rigid alignment of the segment, m.
    pub ate_m: Option<f64>,
    /// Mean NEES of the 6-DOF pose (6 when consistent).
    pub nees: Option<f64>,
    /// Mean NEES of the position (3 when consistent).
    pub nees_position: Option<f64>,
    /// Share of the poses whose position NEES lies in the two-sided 95 % interval of χ²₃.
    pub nees_position_in_95: Option<f64>,
}

impl From<&fastslam::eval::SegmentScore> for SegmentSummary {
    fn from(s: &fastslam::eval::SegmentScore) -> Self {
        Self {
            segment: s.segment,
            samples: s.samples,
            ate_m: finite(s.ate_m),
            nees: finite(s.nees),
            nees_position: finite(s.nees_position),
            nees_position_in_95: finite(s.nees_position_in_95),
        }
    }
}

/// `ate_m.slam`.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct SlamAte {
    /// RMS position error of the SLAM poses, each local map aligned to the truth on its own, m.
    pub slam: Option<f64>,
}

/// `nees`: the SLAM poses' consistency.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct SlamNees {
    /// Mean NEES of the 6-DOF pose over every segment (6 when consistent).
    pub slam: Option<f64>,
    /// Mean NEES of the position (3 when consistent).
    pub slam_position: Option<f64>,
    /// Share of the poses whose position NEES lies in the 95 % interval of χ²₃ (0.95 when consistent).
    pub slam_position_in_95: Option<f64>,
}
