//! The `octree_mapper` process's settings and its pure `step` logic: clouds wait in a bounded
//! queue (the oldest is dropped and counted when insertion falls behind) until the pose at their
//! stamp is known (interpolated between the two poses around it), then go into the occupancy
//! octree ([`octree::OcTree`], OctoMap semantics) and the point statistics of the navigable-space
//! discovery ([`navigable`]). [`stage::OctreeMapperStage`] is the stage around it; `main.rs` one
//! line.

pub mod stage;
pub mod summary;
pub mod voxels;

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use nalgebra::{Isometry3, Vector3};
use navigable::{Discovery, NsdConfig, PointAccumulator};
use octree::{OcTree, SensorModel};
use pipeline_runtime::Validate;
use pipeline_runtime::{Issues, ProcessSettings};
use serde::{Deserialize, Serialize};

/// Which pose places the clouds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum PoseSource {
    /// The fused global pose (`pipeline/fusion/pose`).
    Fused,
    /// The SLAM pose in its local map (`pipeline/slam/pose`; the map frame restarts with each
    /// local map).
    Slam,
    /// The pose each cloud carries in its header (`CLOUD_HAS_POSE`; the simulator's true pose,
    /// or a data set's).
    Cloud,
    /// The 2-D grid SLAM's pose lifted to 3-D (`pipeline/grid_slam/pose3d`, [2D3D] eq 5-9: the
    /// depth camera's pose is the 2-D SLAM pose composed with the camera's mounting).
    GridSlam,
}

/// What the mapper does while insertion is behind the clouds coming in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WhenBehind {
    /// Take no more clouds while `max_pending_clouds` wait: they stay in the service's queue, so
    /// a replay as fast as possible (back-pressure) slows down to the mapper and every cloud is
    /// inserted; a live source drops them for this consumer (counted by the source as
    /// undelivered). The default: a complete map, the same on every run.
    Wait,
    /// Keep taking clouds and drop the oldest waiting one (counted): the newest clouds are
    /// mapped with the least delay, for live operation where the map must keep up.
    DropOldest,
}

/// OctoMap's inverse sensor model (probabilities).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SensorSettings {
    /// P(occupied | hit).
    pub prob_hit: f64,
    /// P(occupied | miss).
    pub prob_miss: f64,
    /// Lower clamp.
    pub clamp_min: f64,
    /// Upper clamp.
    pub clamp_max: f64,
    /// Occupied at or above.
    pub occupancy_threshold: f64,
}

impl Default for SensorSettings {
    fn default() -> Self {
        let m = SensorModel::default();
        Self {
            prob_hit: m.prob_hit,
            prob_miss: m.prob_miss,
            clamp_min: m.clamp_min,
            clamp_max: m.clamp_max,
            occupancy_threshold: m.occupancy_threshold,
        }
    }
}

impl SensorSettings {
    /// As the octree's model.
    pub fn model(&self) -> SensorModel {
        SensorModel {
            prob_hit: self.prob_hit,
            prob_miss: self.prob_miss,
            clamp_min: self.clamp_min,
            clamp_max: self.clamp_max,
            occupancy_threshold: self.occupancy_threshold,
        }
    }
}

/// The depth sensor's mounting on the body (for poses of the body).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SensorMount {
    /// Sensor position in the body frame, m.
    pub offset_m: [f64; 3],
    /// Pitch below body x, deg (optical z along body x when 0).
    pub pitch_down_deg: f64,
}

impl Default for SensorMount {
    fn default() -> Self {
        // The simulator's depth camera.
        Self { offset_m: [0.6, 0.0, -0.3], pitch_down_deg: 40.0 }
    }
}

/// Settings of the `octree_mapper` process.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MapperSettings {
    /// Voxel edge, m.
    pub resolution_m: f64,
    /// Inverse sensor model.
    pub sensor: SensorSettings,
    /// Rays longer than this update free space only up to it, m (< 0: unlimited).
    pub max_range_m: f64,
    /// Which pose places the clouds.
    pub pose_source: PoseSource,
    /// The sensor on the body (not used with `pose_source = "cloud"`).
    pub mount: SensorMount,
    /// Clouds waiting at most (for their pose, or for insertion).
    pub max_pending_clouds: usize,
    /// What happens when `max_pending_clouds` wait: take no more (`"wait"`, default: back-pressure
    /// in a replay, nothing dropped by the mapper) or drop the oldest (`"drop_oldest"`, counted).
    pub when_behind: WhenBehind,
    /// The oldest waiting cloud waits at most this long (wall time) for a pose, s; then it is
    /// dropped (counted).
    pub pose_wait_s: f64,
    /// Largest time between the two poses a cloud's pose is interpolated between, s.
    pub max_pose_gap_s: f64,
    /// Ray-casting threads of the octree.
    pub ray_threads: usize,
    /// `pipeline/map/stats` rate, Hz.
    pub stats_rate_hz: f64,
    /// `pipeline/map/voxels` rate (occupied leaves with their class), Hz; 0 = only at the end.
    pub voxels_rate_hz: f64,
    /// A full voxel set at least this often, s; the messages between carry only the voxels
    /// that changed ([`voxels`]); 0 = every message is a full set.
    pub voxels_full_interval_s: f64,
    /// Navigable space and obstacles.
    pub nsd: NsdConfig,
    /// Obstacles of each scan are associated with the obstacle landmarks of the earlier scans
    /// when their Bhattacharyya distance is at most this ([6D] §VI); 0 turns the per-scan
    /// obstacle tracking off.
    pub obstacle_max_bhattacharyya: f64,
    /// The processes whose end of stream ends this one's input.
    pub end_after: Vec<String>,
    /// At the end, rebuild the map from the clouds kept in memory, each at its pose on this
    /// trajectory (TUM, relative to the output directory; e.g. `grid_slam.tum`, the final best
    /// particle's path, written by grid_slam at its end: list grid_slam in `end_after`), so that
    /// loop closures correct the 3-D map too. The live map is kept as `map_live.bt`; `map.bt`
    /// and the navigable-space layers are the rebuilt map's. Empty: no rebuild.
    pub rebuild_from: String,
    /// Most clouds kept for the rebuild (the oldest are let go beyond it, counted).
    pub rebuild_max_clouds: usize,
    /// Period of the occupancy checkpoint (the snapshot `map.bt` of the runtime's restart state,
    /// `<out>/state/<process>/map.bt`) a restarted mapper starts
    /// from, s (0 = none: a restarted mapper starts with an empty map).
    pub checkpoint_interval_s: f64,
    /// Period of the plane fits' refresh during the run (wall time), s: the voxels that gained
    /// points since the last refresh get their plane fit, so that the navigable-space discovery
    /// at the end fits only what changed after the last one (0 = none: it fits every voxel).
    pub fits_refresh_interval_s: f64,
    /// Period of a discovery of the navigable space during the run (wall time), s, whose 2.5-D
    /// traversability grid goes out on `pipeline/map/traversability` (the viewer's and the ROS 2
    /// gateway's `traversability`) for a planner that runs beside the mapper. Each takes what the
    /// discovery at the end takes on the map so far (the main job's end: about 1-2 s on two
    /// cores, while the insertion waits), so it is for small maps; 0 = none: the grid goes out
    /// once, after the discovery at the end of stream.
    pub traversability_interval_s: f64,
    /// At the end, score the navigable space and the obstacles against the simulated scene's
    /// truth in this file (relative to the output directory; the `sim` and `indoor` sources
    /// write `scene.json`): summary.json `octree_mapper.truth`. Empty: no scoring.
    pub truth_scene: String,
    /// A voxel belongs to a surface of the scene when the mean of its points lies within this of
    /// it, m (0: the voxel size).
    pub truth_tolerance_m: f64,
}

impl Default for MapperSettings {
    fn default() -> Self {
        Self {
            resolution_m: 0.1,
            sensor: SensorSettings::default(),
            max_range_m: 14.0,
            pose_source: PoseSource::Fused,
            mount: SensorMount::default(),
            max_pending_clouds: 64,
            when_behind: WhenBehind::Wait,
            pose_wait_s: 2.0,
            max_pose_gap_s: 1.0,
            ray_threads: 2,
            stats_rate_hz: 1.0,
            voxels_rate_hz: 1.0,
            voxels_full_interval_s: 30.0,
            nsd: NsdConfig::default(),
            obstacle_max_bhattacharyya: 1.0,
            end_after: vec!["ingest".into(), "fusion".into()],
            checkpoint_interval_s: 10.0,
            fits_refresh_interval_s: 5.0,
            traversability_interval_s: 0.0,
            rebuild_from: String::new(),
            rebuild_max_clouds: 5000,
            truth_scene: String::new(),
            truth_tolerance_m: 0.0,
        }
    }
}

impl ProcessSettings for MapperSettings {
    fn shm_estimate_bytes(&self, _extra_subscribers: usize) -> u64 {
        // Stats, the voxel slice and the traversability grid's (both grow by powers of two; the
        // main job's grid is 0.8 M cells of 12 bytes).
        (1 << 20) + (64 << 20) + (16 << 20)
    }
}

impl Validate for MapperSettings {
    fn validate(&self, issues: &mut Issues) {
        issues.check(self.resolution_m.is_finite() && self.resolution_m >= 0.001, "resolution_m", "must be >= 0.001");
        if let Err(e) = OcTree::with_model(self.resolution_m.max(0.001), self.sensor.model()) {
            issues.push("sensor", e.to_string());
        }
        issues.check(self.max_pending_clouds >= 1, "max_pending_clouds", "must be >= 1");
        for (k, v) in [("pose_wait_s", self.pose_wait_s), ("max_pose_gap_s", self.max_pose_gap_s)] {
            issues.check(v.is_finite() && v >= 0.0, k, "must be >= 0");
        }
        for (k, v) in [
            ("stats_rate_hz", self.stats_rate_hz),
            ("voxels_rate_hz", self.voxels_rate_hz),
            ("voxels_full_interval_s", self.voxels_full_interval_s),
        ] {
            issues.check(v.is_finite() && v >= 0.0, k, "must be >= 0");
        }
        issues.check(self.ray_threads >= 1, "ray_threads", "must be >= 1");
        for (k, v) in [
            ("checkpoint_interval_s", self.checkpoint_interval_s),
            ("fits_refresh_interval_s", self.fits_refresh_interval_s),
            ("traversability_interval_s", self.traversability_interval_s),
        ] {
            issues.check(v.is_finite() && v >= 0.0, k, "must be >= 0");
        }
        issues.check(
            self.obstacle_max_bhattacharyya.is_finite() && self.obstacle_max_bhattacharyya >= 0.0,
            "obstacle_max_bhattacharyya",
            "must be >= 0",
        );
        issues.check(
            self.truth_tolerance_m.is_finite() && self.truth_tolerance_m >= 0.0,
            "truth_tolerance_m",
            "must be >= 0 (0: the voxel size)",
        );
        issues.nested("nsd", &self.nsd);
    }
}

pub use geometry::trajectory::{PoseBuffer, PoseLookup};

/// A cloud waiting for its pose.
#[derive(Debug, Clone)]
pub struct PendingCloud {
    /// Stamp, ns.
    pub stamp_ns: u64,
    /// Points in the sensor frame, m.
    pub points_sensor_m: Vec<[f32; 3]>,
    /// When it entered the pipeline (CLOCK_MONOTONIC, ns; 0 unknown).
    pub origin_ns: u64,
    /// The cloud's own `world_from_sensor`, when its header has one.
    pub own_pose: Option<Isometry3<f64>>,
    /// When it arrived.
    pub received: Instant,
}

/// Counters.
#[derive(Debug, Clone, Default, Serialize, Deserialize, schemars::JsonSchema)]
pub struct MapperCounters {
    /// Clouds inserted.
    pub clouds_inserted: u64,
    /// Clouds dropped because insertion fell behind (`when_behind = "drop_oldest"` and the
    /// queue was full).
    pub clouds_dropped_behind: u64,
    /// Clouds that never reached this process (gaps in the publisher's sequence numbers: a live
    /// source's sample dropped for a full queue, or a producer that overwrites).
    pub clouds_missed: u64,
    /// Clouds dropped without a pose (none came in time, or the poses around them were too far apart).
    pub clouds_dropped_no_pose: u64,
    /// Points inserted.
    pub points_inserted: u64,
    /// Points skipped (non-finite).
    pub points_skipped: u64,
    /// Scan obstacles associated with an existing obstacle landmark.
    pub obstacles_associated: u64,
    /// Scan obstacles that started a new obstacle landmark.
    pub obstacles_new: u64,
    /// Obstacle landmarks merged into another (their Gaussians came within the gate).
    #[serde(default)]
    pub obstacle_landmarks_merged: u64,
}

/// The process state.
pub struct MapperState {
    settings: MapperSettings,
    body_from_sensor: Isometry3<f64>,
    /// The occupancy map.
    pub tree: OcTree,
    /// End-point statistics for the navigable-space discovery (tracking the voxels that change).
    pub points: PointAccumulator,
    /// The plane fits of `points`' voxels, refreshed during the run
    /// ([`MapperState::refresh_fits`]), so that the discovery at the end fits only the voxels
    /// changed since the last refresh.
    pub fits: navigable::PlaneFits,
    /// Poses.
    pub poses: PoseBuffer,
    /// Clouds waiting.
    pub pending: VecDeque<PendingCloud>,
    /// Since when the oldest waiting cloud waits for its pose (the `pose_wait_s` clock starts
    /// when a cloud is next to insert, not while it queues behind others).
    front_waiting_since: Option<Instant>,
    /// Counters.
    pub counters: MapperCounters,
    /// Insertion time per cloud, ms.
    pub insert_ms: Vec<f64>,
    /// Obstacle landmarks tracked across scans.
    pub obstacles: navigable::ObstacleTracker,
    /// Latency from the cloud entering the pipeline to the octree updated with it, ms.
    pub cloud_to_octree_ms: Vec<f64>,
    /// Clouds kept for the end-of-run rebuild.
    pub kept: VecDeque<KeptCloud>,
    /// With `truth_scene` set: where the points of each voxel truly came from, by the clouds'
    /// own poses (the simulators' true poses), to score the classification without the poses'
    /// error (summary.json `octree_mapper.truth_by_origin`).
    pub true_origins: Option<navigable::truth::TrueOrigins>,
    /// Clouds let go from `kept` (beyond `rebuild_max_clouds`).
    pub kept_dropped: u64,
}

/// A cloud kept for the end-of-run rebuild: stamp (s), points in the sensor frame (m), the
/// cloud's own `world_from_sensor` when its header had one.
pub type KeptCloud = (f64, Vec<[f32; 3]>, Option<Isometry3<f64>>);

/// What a rebuild did.
#[derive(Debug, Clone, Default, Serialize, Deserialize, schemars::JsonSchema)]
pub struct RebuildReport {
    /// The trajectory file.
    pub trajectory: String,
    /// Clouds re-inserted.
    pub clouds: usize,
    /// Clouds without a pose on the trajectory (outside it or in a gap), not inserted.
    pub clouds_without_pose: usize,
    /// Clouds let go before the end (beyond `rebuild_max_clouds`): in the live map only.
    pub clouds_not_kept: u64,
    /// Mean distance between each cloud's live sensor position and its rebuilt one, m (over the
    /// clouds whose live pose is still in the pose buffer: its last 4,096 poses).
    pub mean_pose_change_m: f64,
}

/// An error of the mapper's state: the octree, the navigable-space discovery, or a checkpoint
/// file (named).
#[derive(Debug, thiserror::Error)]
pub enum MapperError {
    /// The occupancy octree refused an operation.
    #[error(transparent)]
    Octree(#[from] octree::OctreeError),
    /// The navigable-space discovery failed (invalid settings).
    #[error(transparent)]
    Navigable(#[from] navigable::NavigableError),
    /// A checkpoint file could not be written or read.
    #[error("{}: {source}", path.display())]
    CheckpointIo {
        /// The file.
        path: std::path::PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// A checkpoint file is not a map this mapper can start from.
    #[error("{}: {what}", path.display())]
    BadCheckpoint {
        /// The file.
        path: std::path::PathBuf,
        /// What is wrong.
        what: String,
    },
}

impl From<MapperError> for pipeline_runtime::StageError {
    fn from(e: MapperError) -> Self {
        pipeline_runtime::StageError::stage(e)
    }
}

impl MapperState {
    /// A new state (settings validated).
    pub fn new(settings: MapperSettings) -> Result<Self, MapperError> {
        let mut tree = OcTree::with_model(settings.resolution_m, settings.sensor.model())?;
        tree.set_ray_threads(settings.ray_threads);
        let m = &settings.mount;
        let body_from_sensor = geometry::body_from_camera(&Vector3::from(m.offset_m), m.pitch_down_deg.to_radians());
        let mut points = PointAccumulator::new(settings.resolution_m);
        points.track_changes();
        Ok(Self {
            points,
            fits: navigable::PlaneFits::new(),
            body_from_sensor,
            tree,
            poses: PoseBuffer::default(),
            pending: VecDeque::new(),
            front_waiting_since: None,
            counters: MapperCounters::default(),
            insert_ms: vec![],
            obstacles: navigable::ObstacleTracker::default(),
            cloud_to_octree_ms: vec![],
            kept: VecDeque::new(),
            kept_dropped: 0,
            true_origins: (!settings.truth_scene.is_empty())
                .then(|| navigable::truth::TrueOrigins::new(settings.resolution_m)),
            settings,
        })
    }

    /// Rebuilds the map (tree, point statistics, obstacle tracks) from the kept clouds at their
    /// poses on `trajectory` (`world_from_body`, sorted by time); the counters of the live run
    /// stay. Returns what it did.
    pub fn rebuild(&mut self, trajectory: &[(f64, Isometry3<f64>)], name: &str) -> Result<RebuildReport, MapperError> {
        let mut fresh = MapperState::new(MapperSettings { rebuild_from: String::new(), ..self.settings.clone() })?;
        let mut buf = PoseBuffer::default();
        // PoseBuffer keeps 4096 poses: feed it in windows as the clouds advance.
        let mut next = 0;
        let mut report =
            RebuildReport { trajectory: name.to_string(), clouds_not_kept: self.kept_dropped, ..Default::default() };
        let (mut moved, mut compared) = (0.0, 0usize);
        let kept = std::mem::take(&mut self.kept);
        for (t, points, own_pose) in &kept {
            while next < trajectory.len() && trajectory[next].0 <= t + self.settings.max_pose_gap_s {
                buf.push(trajectory[next].0, trajectory[next].1);
                next += 1;
            }
            let PoseLookup::Ready(body) = buf.at(*t, self.settings.max_pose_gap_s) else {
                report.clouds_without_pose += 1;
                continue;
            };
            let world_from_sensor = body * self.body_from_sensor;
            if let PoseLookup::Ready(live) = self.poses.at(*t, self.settings.max_pose_gap_s) {
                moved +=
                    ((live * self.body_from_sensor).translation.vector - world_from_sensor.translation.vector).norm();
                compared += 1;
            }
            let c = PendingCloud {
                stamp_ns: (t * 1e9) as u64,
                points_sensor_m: points.clone(),
                origin_ns: 0,
                own_pose: *own_pose,
                received: Instant::now(),
            };
            fresh.insert(&c, &world_from_sensor)?;
            report.clouds += 1;
        }
        report.mean_pose_change_m = if compared > 0 { moved / compared as f64 } else { 0.0 };
        self.tree = fresh.tree;
        self.points = fresh.points;
        // Other points in the voxels: the live map's fits say nothing about them.
        self.fits = navigable::PlaneFits::new();
        self.obstacles = fresh.obstacles;
        self.true_origins = fresh.true_origins;
        self.kept = kept;
        Ok(report)
    }

    /// The occupancy checkpoint: the max-likelihood map as a `.bt` file's bytes.
    pub fn checkpoint(&self) -> Result<Vec<u8>, MapperError> {
        let mut bytes = Vec::new();
        self.tree.write_binary(&mut bytes)?;
        Ok(bytes)
    }

    /// Starts from a checkpoint a killed instance wrote: its occupied and free voxels at the
    /// clamping log-odds (a `.bt` keeps the max-likelihood map only). `Ok(false)` without one.
    /// The points per voxel behind the navigable-space layers are not in it.
    pub fn restore_checkpoint(&mut self, path: &std::path::Path) -> Result<bool, MapperError> {
        let file = match std::fs::File::open(path) {
            Ok(f) => f,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(false),
            Err(source) => return Err(MapperError::CheckpointIo { path: path.to_path_buf(), source }),
        };
        let mut tree = OcTree::read_binary_with_model(std::io::BufReader::new(file), self.settings.sensor.model())
            .map_err(|e| MapperError::BadCheckpoint { path: path.to_path_buf(), what: e.to_string() })?;
        if (tree.resolution() - self.settings.resolution_m).abs() > 1e-9 {
            return Err(MapperError::BadCheckpoint {
                path: path.to_path_buf(),
                what: format!("resolution {} m, the settings say {} m", tree.resolution(), self.settings.resolution_m),
            });
        }
        tree.set_ray_threads(self.settings.ray_threads);
        self.tree = tree;
        Ok(true)
    }

    /// The settings.
    pub fn settings(&self) -> &MapperSettings {
        &self.settings
    }

    /// True while the mapper takes more clouds: always with `when_behind = "drop_oldest"`, else
    /// while fewer than `max_pending_clouds` wait.
    pub fn takes_clouds(&self) -> bool {
        self.settings.when_behind == WhenBehind::DropOldest || self.pending.len() < self.settings.max_pending_clouds
    }

    /// Queues a cloud; when `max_pending_clouds` already wait, drops the oldest (counted).
    pub fn push_cloud(&mut self, cloud: PendingCloud) {
        while self.pending.len() >= self.settings.max_pending_clouds {
            self.pending.pop_front();
            self.front_waiting_since = None;
            self.counters.clouds_dropped_behind += 1;
        }
        self.pending.push_back(cloud);
    }

    /// When the oldest cloud stops waiting for its pose (`None`: it is not waiting for one).
    pub fn next_deadline(&self) -> Option<Instant> {
        self.front_waiting_since.map(|t| t + Duration::from_secs_f64(self.settings.pose_wait_s))
    }

    /// The process's `step`: inserts at most `max_clouds` clouds whose pose is known, in order;
    /// drops clouds that can have none. `flush` (the inputs ended) ends the waits.
    pub fn step(&mut self, now: Instant, flush: bool, max_clouds: usize) -> Result<usize, MapperError> {
        let mut inserted = 0;
        while inserted < max_clouds
            && let Some(c) = self.pending.front()
        {
            let world_from_sensor = if self.settings.pose_source == PoseSource::Cloud {
                c.own_pose
            } else {
                match self.poses.at(c.stamp_ns as f64 / 1e9, self.settings.max_pose_gap_s) {
                    PoseLookup::Ready(p) => Some(p * self.body_from_sensor),
                    PoseLookup::Wait
                        if !flush
                            && now
                                .saturating_duration_since(*self.front_waiting_since.get_or_insert(now))
                                .as_secs_f64()
                                < self.settings.pose_wait_s =>
                    {
                        break;
                    }
                    _ => None,
                }
            };
            let c = self.pending.pop_front().expect("front exists");
            self.front_waiting_since = None;
            let Some(world_from_sensor) = world_from_sensor else {
                self.counters.clouds_dropped_no_pose += 1;
                continue;
            };
            self.insert(&c, &world_from_sensor)?;
            inserted += 1;
        }
        Ok(inserted)
    }

    fn insert(&mut self, c: &PendingCloud, world_from_sensor: &Isometry3<f64>) -> Result<(), MapperError> {
        let t0 = Instant::now();
        let origin = world_from_sensor.translation.vector;
        let world: Vec<[f32; 3]> = c
            .points_sensor_m
            .iter()
            .map(|p| {
                let w =
                    world_from_sensor.transform_point(&nalgebra::Point3::new(p[0] as f64, p[1] as f64, p[2] as f64));
                [w.x as f32, w.y as f32, w.z as f32]
            })
            .collect();
        let stats =
            self.tree.insert_point_cloud(&world, [origin.x, origin.y, origin.z], self.settings.max_range_m, false)?;
        let max_range = if self.settings.max_range_m < 0.0 { f64::INFINITY } else { self.settings.max_range_m };
        let mut scan = PointAccumulator::new(self.settings.resolution_m);
        let mut origins = self.true_origins.as_mut().zip(c.own_pose.as_ref());
        for (p, s) in world.iter().zip(&c.points_sensor_m) {
            let v = Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            if (v - origin).norm() <= max_range {
                scan.add(&v);
                if let Some((o, own)) = origins.as_mut() {
                    let t = own.transform_point(&nalgebra::Point3::new(s[0] as f64, s[1] as f64, s[2] as f64));
                    o.add(scan.key(&v), &t.coords);
                }
            }
        }
        self.points.merge(&scan)?;
        if self.settings.obstacle_max_bhattacharyya > 0.0 {
            let reg = (self.settings.resolution_m * 0.5).powi(2); // a voxel's extent: flat obstacles
            let u = self.obstacles.update(&scan, &self.settings.nsd, self.settings.obstacle_max_bhattacharyya, reg)?;
            self.counters.obstacles_associated += u.associated;
            self.counters.obstacles_new += u.new;
            self.counters.obstacle_landmarks_merged += u.merged;
        }
        if !self.settings.rebuild_from.is_empty() {
            self.kept.push_back((c.stamp_ns as f64 / 1e9, c.points_sensor_m.clone(), c.own_pose));
            while self.kept.len() > self.settings.rebuild_max_clouds.max(1) {
                self.kept.pop_front();
                self.kept_dropped += 1;
            }
        }
        self.counters.clouds_inserted += 1;
        self.counters.points_inserted += (stats.points - stats.skipped_points) as u64;
        self.counters.points_skipped += stats.skipped_points as u64;
        self.insert_ms.push(t0.elapsed().as_secs_f64() * 1e3);
        if c.origin_ns > 0 {
            let now = pipeline_runtime::clock::monotonic_ns();
            self.cloud_to_octree_ms.push(now.saturating_sub(c.origin_ns) as f64 / 1e6);
        }
        Ok(())
    }

    /// Fits a plane to each voxel that gained points since the last refresh, and keeps the fits
    /// for [`MapperState::discover`]. Returns the voxels fitted.
    pub fn refresh_fits(&mut self) -> usize {
        let changed = self.points.take_changed();
        let before = self.fits.fitted();
        self.fits.refresh(&self.points, changed);
        (self.fits.fitted() - before) as usize
    }

    /// Navigable space and obstacles over the occupied voxels of the map (with the plane fits
    /// kept by [`MapperState::refresh_fits`] where the voxels did not change since).
    pub fn discover(&self) -> Result<Discovery, MapperError> {
        let res = self.settings.resolution_m;
        let tree = &self.tree;
        // Occupied, observed free, or unknown: the free space says from which side a surface was
        // seen (a ceiling is no ground).
        let cell = |k: &navigable::VoxelKey| {
            let c = [(k[0] as f64 + 0.5) * res, (k[1] as f64 + 0.5) * res, (k[2] as f64 + 0.5) * res];
            match tree.search(c) {
                Some(l) if tree.is_occupied_log_odds(l) => navigable::MapCell::Occupied,
                Some(_) => navigable::MapCell::Free,
                None => navigable::MapCell::Unknown,
            }
        };
        Ok(navigable::discover_in(&self.points, cell, &self.settings.nsd, &self.fits)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_checkpoint_restores_the_occupied_and_free_voxels_and_a_wrong_resolution_is_an_error() {
        let dir = std::env::temp_dir().join(format!("mapper-checkpoint-{}", std::process::id()));
        let path = dir.join("map.bt");
        let mut st = MapperState::new(MapperSettings::default()).expect("state");
        assert!(!st.restore_checkpoint(&path).expect("no checkpoint is not an error"));
        let wall: Vec<[f32; 3]> = (0..400).map(|i| [3.0, (i % 20) as f32 * 0.1, (i / 20) as f32 * 0.1]).collect();
        st.tree.insert_point_cloud(&wall, [0.0f32, 0.5, 0.5], 10.0, false).expect("insert");
        std::fs::create_dir_all(&dir).expect("dir");
        std::fs::write(&path, st.checkpoint().expect("checkpoint")).expect("write");
        let (occupied, free) = st.tree.num_occupied_free_leaves();
        assert!(occupied > 0 && free > 0);
        let mut restored = MapperState::new(MapperSettings::default()).expect("state");
        assert!(restored.restore_checkpoint(&path).expect("restore"));
        assert_eq!(restored.tree.num_occupied_free_leaves(), (occupied, free));
        let mut coarse = MapperState::new(MapperSettings { resolution_m: 0.2, ..Default::default() }).expect("state");
        let e = coarse.restore_checkpoint(&path).unwrap_err().to_string();
        assert!(e.contains("map.bt") && e.contains("resolution"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    fn cloud(stamp_s: f64, now: Instant) -> PendingCloud {
        // A wall 3 m in front of the sensor (optical z).
        let pts = (0..100).map(|i| [(i % 10) as f32 * 0.05 - 0.25, (i / 10) as f32 * 0.05 - 0.25, 3.0]).collect();
        PendingCloud {
            stamp_ns: (stamp_s * 1e9) as u64,
            origin_ns: 0,
            points_sensor_m: pts,
            own_pose: None,
            received: now,
        }
    }

    #[test]
    fn clouds_wait_for_their_pose_and_the_oldest_is_dropped_when_behind() {
        let settings =
            MapperSettings { max_pending_clouds: 2, when_behind: WhenBehind::DropOldest, ..Default::default() };
        let mut st = MapperState::new(settings).unwrap();
        let now = Instant::now();
        for k in 0..3 {
            assert!(st.takes_clouds());
            st.push_cloud(cloud(1.0 + k as f64 * 0.2, now));
        }
        assert_eq!(st.counters.clouds_dropped_behind, 1);
        assert_eq!(st.step(now, false, 10).unwrap(), 0, "no pose yet");
        st.poses.push(1.0, Isometry3::identity());
        st.poses.push(2.0, Isometry3::translation(1.0, 0.0, 0.0));
        assert_eq!(st.step(now, false, 10).unwrap(), 2);
        assert_eq!(st.counters.clouds_inserted, 2);
        assert!(st.tree.num_leaves() > 0);
        // A cloud whose pose never comes is dropped pose_wait_s after it is next to insert.
        st.push_cloud(cloud(5.0, now));
        assert_eq!(st.next_deadline(), None, "not waiting yet");
        assert_eq!(st.step(now + Duration::from_secs(10), false, 10).unwrap(), 0);
        assert_eq!(st.counters.clouds_dropped_no_pose, 0, "the wait starts when it is next, not when it came");
        assert_eq!(st.next_deadline(), Some(now + Duration::from_secs(12)));
        assert_eq!(st.step(now + Duration::from_secs(13), false, 10).unwrap(), 0);
        assert_eq!(st.counters.clouds_dropped_no_pose, 1);
        assert!(st.pending.is_empty());
        assert_eq!(st.next_deadline(), None);
    }

    #[test]
    fn by_default_a_full_queue_takes_no_more_clouds_and_drops_none() {
        let settings = MapperSettings { max_pending_clouds: 2, ..Default::default() };
        let mut st = MapperState::new(settings).unwrap();
        let now = Instant::now();
        st.push_cloud(cloud(1.0, now));
        assert!(st.takes_clouds());
        st.push_cloud(cloud(1.2, now));
        assert!(!st.takes_clouds(), "two wait: the rest stays in the service's queue");
        st.poses.push(1.0, Isometry3::identity());
        st.poses.push(2.0, Isometry3::translation(1.0, 0.0, 0.0));
        assert_eq!(st.step(now, false, 1).unwrap(), 1);
        assert!(st.takes_clouds());
        assert_eq!(st.counters.clouds_dropped_behind, 0);
    }

    #[test]
    fn an_obstacle_seen_in_two_scans_is_one_landmark() {
        let settings = MapperSettings { pose_source: PoseSource::Cloud, ..Default::default() };
        let mut st = MapperState::new(settings).unwrap();
        let now = Instant::now();
        // A 0.3 m bush 3 m ahead (points filling a volume: non-planar in every voxel), seen
        // twice from slightly different sensor positions.
        let frac = |x: f32| x - x.floor();
        let blob: Vec<[f32; 3]> = (0..3000)
            .map(|i| {
                let i = i as f32;
                [0.3 * frac(i * 0.618) - 0.15, 0.3 * frac(i * 0.414) - 0.15, 3.0 + 0.3 * frac(i * 0.732) - 0.15]
            })
            .collect();
        for dx in [0.0, 0.05] {
            st.push_cloud(PendingCloud {
                stamp_ns: 0,
                origin_ns: 0,
                points_sensor_m: blob.iter().map(|p| [p[0] - dx, p[1], p[2]]).collect(),
                own_pose: Some(Isometry3::translation(dx as f64, 0.0, 0.0)),
                received: now,
            });
        }
        assert_eq!(st.step(now, false, 10).unwrap(), 2);
        assert!(st.counters.obstacles_new >= 1, "{:?}", st.counters);
        assert!(st.counters.obstacles_associated >= 1, "the second scan's blob matches the first: {:?}", st.counters);
        assert_eq!(st.obstacles.landmarks.iter().filter(|l| l.scans == 2).count(), 1);
    }

    #[test]
    fn plane_fits_refreshed_during_the_run_leave_only_the_changed_voxels_to_the_end() {
        let settings = MapperSettings { pose_source: PoseSource::Cloud, ..Default::default() };
        let mut st = MapperState::new(settings.clone()).unwrap();
        let now = Instant::now();
        // A floor 2 m below the sensor (the pose has no rotation: the points are in the world's
        // axes), seen from positions 0.5 m apart. (At z +2 m it would be a ceiling, seen from
        // below, and no region.)
        let floor: Vec<[f32; 3]> =
            (0..4000).map(|i| [(i % 80) as f32 * 0.025 - 1.0, (i / 80) as f32 * 0.025 - 0.6, -2.0]).collect();
        let push = |st: &mut MapperState, x: f64| {
            st.push_cloud(PendingCloud {
                stamp_ns: 0,
                origin_ns: 0,
                points_sensor_m: floor.clone(),
                own_pose: Some(Isometry3::translation(x, 0.0, 0.0)),
                received: now,
            });
            assert_eq!(st.step(now, false, 10).unwrap(), 1);
        };
        for x in [0.0, 0.5, 1.0] {
            push(&mut st, x);
        }
        let fitted = st.refresh_fits();
        assert_eq!(fitted, st.points.cells().len(), "every voxel so far");
        assert_eq!(st.discover().unwrap().fitted, 0, "nothing changed since the refresh");
        push(&mut st, 1.5);
        let d = st.discover().unwrap();
        assert!(d.fitted > 0 && d.fitted < d.classes.len(), "{} of {} fitted at the end", d.fitted, d.classes.len());
        let fresh = navigable::discover(&st.points, |_| true, &settings.nsd).unwrap();
        assert_eq!((d.regions.len(), d.counts()), (fresh.regions.len(), fresh.counts()));
        assert!(!d.regions.is_empty(), "the floor");
        // A rebuild replaces the points: no fit of the live map is kept for them.
        st.kept.clear();
        st.rebuild(&[], "none").unwrap();
        assert!(st.fits.is_empty());
    }

    #[test]
    fn the_wall_ends_up_occupied_in_front_of_the_sensor() {
        let mut st = MapperState::new(MapperSettings { pose_source: PoseSource::Cloud, ..Default::default() }).unwrap();
        let now = Instant::now();
        let mut c = cloud(1.0, now);
        c.own_pose = Some(Isometry3::identity()); // sensor frame = world
        st.push_cloud(c);
        assert_eq!(st.step(now, false, 10).unwrap(), 1);
        assert_eq!(st.tree.is_occupied([0.0f64, 0.0, 3.0]), Some(true));
        assert_eq!(st.tree.is_occupied([0.0f64, 0.0, 1.5]), Some(false), "free along the rays");
        assert_eq!(st.tree.search([0.0f64, 0.0, 5.0]), None, "unknown behind the wall");
    }
}
