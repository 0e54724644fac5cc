//! The octree mapper's part of summary.json (`octree_mapper`, and `pipeline_latency_ms.cloud_to_octree`),
//! described in docs/summary.schema.json.

use pipeline_runtime::summary::{CountedPercentiles, Percentiles};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::voxels::VoxelStreamCounters;
use crate::{MapperCounters, PoseSource, RebuildReport};

/// What the `octree_mapper` stage adds to summary.json.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct OctreeMapperPart {
    /// The map.
    pub octree_mapper: MapperSummary,
    /// Latency from a depth cloud to its insertion (at the end of stream).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pipeline_latency_ms: Option<MapperLatency>,
}

/// `octree_mapper`: the occupancy map, navigable space and obstacles.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct MapperSummary {
    /// Voxel edge, m.
    pub resolution_m: f64,
    /// True when the run was stopped before the end of stream (only the map so far was written).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub stopped_early: bool,
    /// Which pose placed the clouds (at the end of stream).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pose_source: Option<PoseSource>,
    /// Leaves of the octree.
    pub leaves: usize,
    /// Occupied leaves.
    pub occupied_leaves: usize,
    /// Free leaves.
    pub free_leaves: usize,
    /// What the octree holds in memory, bytes (at the end of stream).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub memory_bytes: Option<usize>,
    /// Clouds and points inserted, dropped and skipped.
    pub counters: MapperCounters,
    /// The end of stream's navigable space and obstacles ([6D]), and how the voxels were streamed.
    #[serde(flatten, deserialize_with = "pipeline_runtime::summary::flattened_option")]
    pub end_of_stream: Option<MapperEnd>,
}

/// What only the end of stream reports.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct MapperEnd {
    /// Insertion time per cloud, ms.
    pub insert_ms: Percentiles,
    /// Occupied voxels by class.
    pub voxels: VoxelClasses,
    /// Navigable regions (grown from voxels whose best-fit planes meet).
    pub navigable_regions: usize,
    /// Their total area, m².
    pub navigable_area_m2: f64,
    /// Obstacles (the non-planar rest, as components).
    pub obstacles: usize,
    /// Walls (large steep planes with no top: a building's walls; not obstacles, but they block
    /// as obstacles do in the traversability grid).
    #[serde(default)]
    pub walls: usize,
    /// Obstacle landmarks tracked across scans.
    pub obstacle_landmarks: usize,
    /// Of those, the ones seen in two or more scans.
    pub obstacle_landmarks_seen_in_2_or_more_scans: usize,
    /// The map rebuilt along the final trajectory (`rebuild_from`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rebuild: Option<RebuildReport>,
    /// The voxel stream to the viewer and the bridge.
    pub voxel_stream: VoxelStreamSummary,
    /// Navigable space and obstacles against the simulated scene's truth (`truth_scene`: the
    /// underwater scene's seabed, rocks and wreck, or the indoor scene's floor and boxes).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub truth: Option<navigable::truth::TruthScore>,
    /// The same, each voxel judged where its points truly came from (by the clouds' own poses,
    /// which the simulators set to the true ones) instead of where the map put them: the
    /// classification alone, without the poses' error (`null` when the clouds carry no pose).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub truth_by_origin: Option<navigable::truth::TruthScore>,
    /// What the end of the run took.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub end_of_run: Option<EndOfRunWork>,
}

/// The end of the run's work (wall time), and how much of the navigable-space discovery the
/// plane fits refreshed during the run (`fits_refresh_interval_s`) left to it.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct EndOfRunWork {
    /// Writing `map.bt`, ms.
    pub map_bt_ms: f64,
    /// The navigable-space discovery (plane fits, regions, obstacles), ms.
    pub navigable_ms: f64,
    /// The PLY layers, the traversability grid, the classified voxels and the truth's score, ms.
    pub layers_ms: f64,
    /// Occupied voxels the discovery classified.
    pub voxels_discovered: usize,
    /// Of those, the ones it fitted a plane to itself (changed since the last refresh, or all
    /// without refreshes).
    pub voxels_fitted: usize,
}

/// Occupied voxels by class.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct VoxelClasses {
    /// Planar and level enough to stand on.
    pub navigable: usize,
    /// Planar but too steep.
    pub steep: usize,
    /// Not planar.
    pub non_planar: usize,
    /// Too few points to fit a plane (or points along a line).
    pub sparse: usize,
    /// Planar and level, in a patch smaller than `nsd.min_region_area_m2` touching no obstacle.
    pub patch: usize,
    /// Part of a wall (`walls`).
    #[serde(default)]
    pub wall: usize,
}

/// `octree_mapper.voxel_stream`: messages and MB of full sets and deltas, and the MB a stream of
/// full sets only would have taken at the same rate.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct VoxelStreamSummary {
    /// Full sets sent.
    pub full_messages: u64,
    /// Deltas sent.
    pub delta_messages: u64,
    /// Payload of the full sets, MB.
    pub full_mb: f64,
    /// Payload of the deltas, MB.
    pub delta_mb: f64,
    /// Voxels sent as removed.
    pub removed_voxels: u64,
    /// Full sets sent because a command asked for one.
    pub snapshots_requested: u64,
    /// Payload had every message been a full set, MB.
    pub full_sets_only_mb: f64,
    /// The stream's rate, MB/s.
    pub mb_per_s: f64,
    /// Messages for which the whole map was read.
    pub whole_map_reads: u64,
    /// Changed regions read instead.
    pub regions_read: u64,
    /// Voxels read in the changed regions.
    pub region_voxels_read: u64,
    /// Time spent making the messages, s.
    pub build_s: f64,
}

impl From<&VoxelStreamCounters> for VoxelStreamSummary {
    fn from(c: &VoxelStreamCounters) -> Self {
        let mb = |b: u64| b as f64 / 1e6;
        Self {
            full_messages: c.full_messages,
            delta_messages: c.delta_messages,
            full_mb: mb(c.full_bytes),
            delta_mb: mb(c.delta_bytes),
            removed_voxels: c.removed,
            snapshots_requested: c.snapshots_requested,
            full_sets_only_mb: mb(c.full_only_bytes),
            mb_per_s: if c.span_s > 0.0 { mb(c.full_bytes + c.delta_bytes) / c.span_s } else { 0.0 },
            whole_map_reads: c.whole_map_reads,
            regions_read: c.regions_read,
            region_voxels_read: c.region_voxels_read,
            build_s: c.build_s,
        }
    }
}

/// `pipeline_latency_ms` (the mapper's key), ms.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct MapperLatency {
    /// From a depth cloud's origin to its insertion into the map (`null` when the run stopped
    /// before the end of stream; the key is shared with fusion's latencies).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cloud_to_octree: Option<CountedPercentiles>,
}
