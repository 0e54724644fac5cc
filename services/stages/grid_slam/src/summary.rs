//! The grid SLAM process's part of summary.json (`grid_slam`, and `ate_m.grid_slam` when a
//! ground truth is there), described in docs/summary.schema.json.

use std::collections::BTreeMap;

use grid_slam::NeffSummary;
use grid_slam::backend::BackEndReport;
use grid_slam::relations::RelationScore;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::BackEndKind;

/// What the `grid_slam` stage adds to summary.json.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct GridSlamPart {
    /// The filter's and the back end's run.
    pub grid_slam: GridSlamSummary,
    /// Accuracy against the ground truth (when the source wrote one).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ate_m: Option<GridSlamAte>,
}

/// `grid_slam`: scans, updates, the weights, memory, the back end, the relations' score.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct GridSlamSummary {
    /// Scans processed (0 when none came: then only `rejected` follows).
    pub scans: u64,
    /// Inputs refused, by reason.
    pub rejected: BTreeMap<String, u64>,
    /// The rest, once a scan was processed.
    #[serde(flatten, deserialize_with = "pipeline_runtime::summary::flattened_option")]
    pub run: Option<GridSlamRun>,
}

/// What a run that processed scans reports.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct GridSlamRun {
    /// Filter updates (every `linear_update_m` or `angular_update_rad` of motion).
    pub updates: u64,
    /// Resamplings.
    pub resamples: u64,
    /// How peaked the weights were (`null` before the first update).
    pub n_eff: Option<NeffSummary>,
    /// Particles.
    pub particles: usize,
    /// Grid cell size, m.
    pub resolution_m: f64,
    /// Planar poses published.
    pub poses_published: u64,
    /// Occupancy grids published.
    pub grids_published: u64,
    /// Particle sets published.
    pub particle_sets_published: u64,
    /// Beams left out (NaN, negative, below the minimum range).
    pub invalid_beams: u64,
    /// Scans the matcher could not place (the odometry's pose taken).
    pub tracking_failures: u64,
    /// Updates whose proposal fell back to the motion model.
    pub proposal_fallbacks: u64,
    /// Scan matches at filter updates, each with its proposal: one per particle and update,
    /// less one for each copy that shared its parent's after a resampling (copies have the
    /// same pose and map).
    #[serde(default)]
    pub update_matches: u64,
    /// The particles' maps in memory.
    pub memory: GridMemory,
    /// The final grid's files and geometry (`null` when there is none).
    pub grid: Option<GridFiles>,
    /// The trajectory file (`grid_slam.tum`).
    pub trajectory: String,
    /// The pose-graph back end.
    pub back_end: BackEndSummary,
    /// Wall time from the start to the summary, s.
    pub wall_s: f64,
    /// The final trajectory's score against the relations (`relations`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub relations: Option<RelationScore>,
    /// The filter's own trajectory's score, before the back end.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub relations_front_end: Option<RelationScore>,
}

/// `grid_slam.memory`.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct GridMemory {
    /// The particles' distinct tiles and deltas at their largest, bytes.
    pub peak_bytes: Option<usize>,
    /// The best particle's map alone at the end, bytes.
    pub one_map_bytes: usize,
    /// Tiles written at updates that became deltas over another particle's.
    pub tiles_shared: u64,
    /// peak_bytes / one_map_bytes.
    pub peak_over_one_map: Option<f64>,
}

/// `grid_slam.grid`: the map_server files.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct GridFiles {
    /// The image.
    pub pgm: String,
    /// Its map_server description.
    pub yaml: String,
    /// The picture with the path.
    pub png: String,
    /// Cells across.
    pub width: usize,
    /// Cells down.
    pub height: usize,
    /// Cell size, m.
    pub resolution_m: f64,
    /// The lower-left corner in the map frame, m.
    pub origin_m: [f64; 2],
}

/// `grid_slam.back_end`.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct BackEndSummary {
    /// Which back end (`pose_graph` or `none`).
    pub kind: BackEndKind,
    /// What it did (`null` without one, or when it failed).
    pub report: Option<BackEndReport>,
    /// Its wall time, s.
    pub wall_s: f64,
    /// Why it failed, if it did (the filter's trajectory is written instead).
    pub error: Option<String>,
    /// The scans it keeps, bytes.
    pub scans_bytes: Option<usize>,
}

/// `ate_m.grid_slam`.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct GridSlamAte {
    /// RMS planar position error at the ground truth's stamps (nearest, no alignment), m.
    pub grid_slam: Option<f64>,
}
