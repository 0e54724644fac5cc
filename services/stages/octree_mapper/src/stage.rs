//! The octree mapper as a [`Stage`]: its ports, checkpoints and map publishing around
//! [`MapperState`]. It ends after every process in `end_after` has ended (empty: the first),
//! once the cloud service's queue and its own are empty.

use pipeline_runtime::StageError;
use std::time::{Duration, Instant};

use pipeline_runtime::stage::{EndAfter, Ending, Stage, Step};
use pipeline_runtime::{Input, Output, ProcessContext, Restart, Runtime, Wake};

/// The snapshot key of the occupancy checkpoint (`<out>/state/<process>/map.bt`).
const CHECKPOINT: &str = "map.bt";
use shared_types::services::{
    CLOUD, COMMAND, FUSION_POSE, GRID_SLAM_POSE3D, MAP_STATS, MAP_TRAVERSABILITY, MAP_VOXELS, SLAM_POSE,
};
use shared_types::*;

use crate::summary::{
    EndOfRunWork, MapperEnd, MapperLatency, MapperSummary, OctreeMapperPart, VoxelClasses, VoxelStreamSummary,
};
use crate::voxels::{VoxelStream, VoxelStreamCounters};
use crate::{MapperSettings, MapperState, PendingCloud, PoseSource};
use pipeline_runtime::summary::{CountedPercentiles, Percentiles};

fn stats_msg(st: &MapperState, regions: u32, obstacles: u32) -> MapStats {
    let (occ, free) = st.tree.num_occupied_free_leaves();
    let leaves = occ + free;
    MapStats {
        resolution_m: st.tree.resolution(),
        leaves: leaves as u64,
        occupied_leaves: occ as u64,
        free_leaves: free as u64,
        inner_nodes: st.tree.num_nodes().saturating_sub(leaves) as u64,
        memory_bytes: st.tree.memory_usage_bytes() as u64,
        clouds_inserted: st.counters.clouds_inserted,
        clouds_dropped: st.counters.clouds_dropped_behind
            + st.counters.clouds_dropped_no_pose
            + st.counters.clouds_missed,
        points_inserted: st.counters.points_inserted,
        last_insert_ms: st.insert_ms.last().copied().unwrap_or(0.0),
        navigable_regions: regions,
        obstacles,
        ..Default::default()
    }
}

/// The occupied leaves with their class (navigable, obstacle, or just occupied), in wire form.
fn build_voxels(st: &MapperState, classes: Option<&navigable::Discovery>) -> Vec<Voxel> {
    crate::voxels::all_voxels(st, classes)
}

/// Publishes the map's voxels on `pipeline/map/voxels`: a full set or the changes since the
/// last message (`stream`).
/// `classified`: the end of the run's full set with classes (see [`crate::voxels::next_message`]).
fn send_voxels(
    out: &mut Output<[Voxel], VoxelSetHeader>,
    stream: &mut VoxelStream,
    st: &mut MapperState,
    classified: Option<Vec<Voxel>>,
    stamp_ns: u64,
) -> Result<(), StageError> {
    let resolution_m = st.tree.resolution();
    let (kind, payload) = crate::voxels::next_message(stream, st, classified, Instant::now())?;
    let mut s = out.loan_slice_uninit(payload.len())?.write_from_slice(&payload);
    *s.user_header_mut() =
        VoxelSetHeader { msg: MsgHeader { stamp_ns, ..Default::default() }, resolution_m, frame: FRAME_WORLD, kind };
    out.send(s)?;
    Ok(())
}

/// A cloud's insertion that takes longer is reported (the heartbeat goes on meanwhile).
const SLOW_INSERTION: Duration = Duration::from_secs(1);

/// The end-of-run work (map.bt, navigable space, PLY layers, the classified voxels) on a worker
/// thread, while this thread keeps the heartbeats going (a large map takes seconds).
/// Sends `grid` on `pipeline/map/traversability`, written into the loaned slice in place (a
/// grid without cells is not sent). NaN heights and slopes (undefined) go out as 0: the class
/// says what is defined.
fn send_traversability(
    out: &mut Output<[TraversabilityCell], OccupancyGridHeader>,
    grid: &navigable::traversability::TraversabilityGrid,
    stamp_ns: u64,
) -> Result<(), StageError> {
    use navigable::traversability::CellClass;
    let n = grid.width * grid.height;
    if n == 0 {
        return Ok(());
    }
    let defined = |v: f32| if v.is_finite() { v } else { 0.0 };
    let mut s = out.loan_slice_uninit(n)?.write_from_fn(|i| TraversabilityCell {
        height_m: defined(grid.height_m[i]),
        slope_deg: defined(grid.slope_deg[i]),
        class: match grid.class[i] {
            CellClass::Unknown => TRAVERSABILITY_UNKNOWN,
            CellClass::Navigable => TRAVERSABILITY_NAVIGABLE,
            CellClass::Obstacle => TRAVERSABILITY_OBSTACLE,
        },
        _reserved: [0; 3],
    });
    *s.user_header_mut() = OccupancyGridHeader {
        msg: MsgHeader { stamp_ns, ..Default::default() },
        resolution_m: grid.resolution_m,
        origin_m: [grid.origin_m.0, grid.origin_m.1],
        width: grid.width as u32,
        height: grid.height as u32,
    };
    out.send(s)?;
    Ok(())
}

/// What the end of the run computed: the discovery, the voxels with their classes, the 2.5-D
/// traversability grid and the summary part.
type EndOfRunOutputs =
    (navigable::Discovery, Vec<Voxel>, navigable::traversability::TraversabilityGrid, OctreeMapperPart);

fn end_of_run(rt: &mut Runtime, st: &MapperState, out_dir: &std::path::Path) -> Result<EndOfRunOutputs, StageError> {
    std::fs::create_dir_all(out_dir)?;
    type Scores = (Option<navigable::truth::TruthScore>, Option<navigable::truth::TruthScore>);
    type EndOfRun =
        (navigable::Discovery, Vec<Voxel>, navigable::traversability::TraversabilityGrid, Scores, EndOfRunWork);
    let (d, voxels, grid, (truth, truth_by_origin), work) = std::thread::scope(|s| {
        let worker = s.spawn(|| -> Result<EndOfRun, StageError> {
            let t0 = Instant::now();
            st.tree.write_binary_file(out_dir.join("map.bt")).map_err(StageError::stage)?;
            let t1 = Instant::now();
            let d = st.discover()?;
            let t2 = Instant::now();
            // The score against the truth beside the layers (the machine's second core).
            let (voxels, grid, truth) = std::thread::scope(|inner| -> Result<_, StageError> {
                let scoring = inner.spawn(|| {
                    let landmarks: Vec<(nalgebra::Vector3<f64>, u32)> =
                        st.obstacles.landmarks.iter().filter_map(|l| Some((l.stats.mean_cov()?.0, l.scans))).collect();
                    score_against_truth(st.settings(), out_dir, &st.points, st.true_origins.as_ref(), &landmarks, &d)
                });
                navigable::write_navigable_ply(&out_dir.join("navigable.ply"), &st.points, &d)
                    .map_err(StageError::stage)?;
                navigable::write_obstacles_ply(&out_dir.join("obstacles.ply"), &st.points, &d)
                    .map_err(StageError::stage)?;
                navigable::write_walls_ply(&out_dir.join("walls.ply"), &st.points, &d).map_err(StageError::stage)?;
                let grid = navigable::traversability::TraversabilityGrid::from_discovery(&st.points, &d);
                grid.write(out_dir, "traversability").map_err(StageError::stage)?;
                let (nav, blocked, unknown) = grid.counts();
                tracing::info!(
                    "traversability grid {} x {} cells of {} m: {nav} navigable, {blocked} obstacle, {unknown} unknown \
                     (traversability.pgm/.yaml, traversability_height.pfm, traversability_slope.pfm)",
                    grid.width,
                    grid.height,
                    grid.resolution_m
                );
                let voxels = build_voxels(st, Some(&d));
                let truth = scoring.join().map_err(|_| StageError::msg("the truth scoring panicked"))?;
                Ok((voxels, grid, truth))
            })?;
            let work = EndOfRunWork {
                map_bt_ms: (t1 - t0).as_secs_f64() * 1e3,
                navigable_ms: (t2 - t1).as_secs_f64() * 1e3,
                layers_ms: t2.elapsed().as_secs_f64() * 1e3,
                voxels_discovered: d.classes.len(),
                voxels_fitted: d.fitted,
            };
            tracing::info!(
                "end of run: map.bt in {:.0} ms, navigable space in {:.0} ms ({} of {} voxels fitted now, the rest's \
                 fits kept from the run; surfaces {:.1} mm thick, regions do not cross steps over {:.0} mm), PLY \
                 layers, voxels and the truth's score in {:.0} ms",
                work.map_bt_ms,
                work.navigable_ms,
                work.voxels_fitted,
                work.voxels_discovered,
                d.surface_sigma_m * 1e3,
                d.step_m * 1e3,
                work.layers_ms
            );
            Ok((d, voxels, grid, truth, work))
        });
        while !worker.is_finished() {
            rt.keep_alive();
            std::thread::sleep(Duration::from_millis(50));
        }
        worker.join().map_err(|_| StageError::msg("end-of-run worker panicked"))?
    })?;
    let c = d.counts();
    let (occ, free) = st.tree.num_occupied_free_leaves();
    let part = OctreeMapperPart {
        pipeline_latency_ms: Some(MapperLatency {
            cloud_to_octree: Some(CountedPercentiles::of(&st.cloud_to_octree_ms)),
        }),
        octree_mapper: MapperSummary {
            resolution_m: st.tree.resolution(),
            stopped_early: false,
            pose_source: Some(st.settings().pose_source),
            leaves: occ + free,
            occupied_leaves: occ,
            free_leaves: free,
            memory_bytes: Some(st.tree.memory_usage_bytes()),
            counters: st.counters.clone(),
            end_of_stream: Some(MapperEnd {
                insert_ms: Percentiles::of(&st.insert_ms),
                voxels: VoxelClasses {
                    navigable: c.navigable,
                    steep: c.steep,
                    non_planar: c.non_planar,
                    sparse: c.sparse,
                    patch: c.patch,
                    wall: c.wall,
                },
                navigable_regions: d.regions.len(),
                navigable_area_m2: d.regions.iter().map(|r| r.area_m2).sum::<f64>(),
                obstacles: d.obstacles.len(),
                walls: d.walls.len(),
                obstacle_landmarks: st.obstacles.landmarks.len(),
                obstacle_landmarks_seen_in_2_or_more_scans: st
                    .obstacles
                    .landmarks
                    .iter()
                    .filter(|l| l.scans >= 2)
                    .count(),
                rebuild: None,
                voxel_stream: VoxelStreamSummary::from(&VoxelStreamCounters::default()),
                truth,
                truth_by_origin,
                end_of_run: Some(work),
            }),
        },
    };
    tracing::info!(
        clouds = st.counters.clouds_inserted,
        dropped = st.counters.clouds_dropped_behind + st.counters.clouds_dropped_no_pose,
        occupied = occ,
        regions = d.regions.len(),
        obstacles = d.obstacles.len(),
        "map written"
    );
    Ok((d, voxels, grid, part))
}

/// The `octree_mapper` stage.
pub struct OctreeMapperStage {
    settings: MapperSettings,
    st: MapperState,
    checkpoint_every: Option<Duration>,
    last_checkpoint: Instant,
    /// Clouds this instance had inserted at its last checkpoint (those after it are lost from the
    /// map if it is killed).
    inserted_at_checkpoint: u64,
    clouds: Input<[CloudPoint], CloudHeader>,
    fused: Input<FusedPose, MsgHeader>,
    slam: Input<PoseEstimate, MsgHeader>,
    grid_slam: Input<PoseEstimate, MsgHeader>,
    commands: Input<ControlCommand, MsgHeader>,
    stats_out: Output<MapStats, MsgHeader>,
    voxels_out: Output<[Voxel], VoxelSetHeader>,
    traversability_out: Output<[TraversabilityCell], OccupancyGridHeader>,
    voxel_stream: VoxelStream,
    traversability_every: Option<Duration>,
    last_traversability: Instant,
    stats_every: Option<Duration>,
    voxels_every: Option<Duration>,
    fits_every: Option<Duration>,
    last_stats: Instant,
    last_voxels: Instant,
    last_fits: Instant,
    last_stamp: u64,
    last_cloud_seq: Option<u64>,
    /// A restarted instance (its first cloud is not the stream's first).
    restarted: bool,
    out_dir: std::path::PathBuf,
}

/// The discovery `d` scored against the scene in `truth_scene` (`None` when unset; a file
/// that cannot be read is warned about and scores nothing): the underwater simulator's
/// scene (under `scene`) or the indoor one's boxes (`kind = "indoor"`). Each voxel is judged
/// where the map put its points, and (with `origins`) where they truly came from.
fn score_against_truth(
    settings: &MapperSettings,
    out_dir: &std::path::Path,
    points: &navigable::PointAccumulator,
    origins: Option<&navigable::truth::TrueOrigins>,
    landmarks: &[(nalgebra::Vector3<f64>, u32)],
    d: &navigable::Discovery,
) -> (Option<navigable::truth::TruthScore>, Option<navigable::truth::TruthScore>) {
    use navigable::truth::{TruthClass, TruthScore};
    if settings.truth_scene.is_empty() {
        return (None, None);
    }
    let path = out_dir.join(&settings.truth_scene);
    let tolerance = if settings.truth_tolerance_m > 0.0 { settings.truth_tolerance_m } else { points.resolution_m() };
    let file = match std::fs::read(&path)
        .map_err(|e| e.to_string())
        .and_then(|b| serde_json::from_slice::<SceneFile>(&b).map_err(|e| e.to_string()))
    {
        Ok(f) => f,
        Err(e) => {
            tracing::warn!("not scored against the truth: {}: {e}", path.display());
            return (None, None);
        }
    };
    let both = |judge: &(dyn Fn(&nalgebra::Vector3<f64>) -> TruthClass + Sync)| {
        let mut at_map = navigable::truth::score(d, points, judge);
        at_map.landmarks = Some(navigable::truth::score_landmarks(landmarks, 2, judge));
        let by_origin = origins.filter(|o| !o.is_empty()).map(|o| o.score(d, judge));
        (at_map, by_origin)
    };
    // The rocks' count in an underwater scene: the objects before it are rocks, the one at it
    // the wreck.
    let (rocks, (at_map, by_origin)) = match file {
        SceneFile::Underwater { scene } => {
            let rocks = scene.rocks.len() as u32;
            let scores = both(&|p| match scene.truth_at(p, tolerance) {
                sim::scene::SceneTruth::Seabed => TruthClass::Ground,
                sim::scene::SceneTruth::Rock(i) => TruthClass::Object(i as u32),
                sim::scene::SceneTruth::Wreck => TruthClass::Object(rocks),
                sim::scene::SceneTruth::Nothing => TruthClass::Nothing,
            });
            (Some(rocks), scores)
        }
        SceneFile::Indoor { boxes } => {
            let truth = sim::indoor::IndoorTruth::new(boxes.iter().map(|b| (b.min, b.max, b.what.as_str())));
            let scores = both(&|p| match truth.at(p, tolerance) {
                sim::indoor::IndoorTruthAt::Floor => TruthClass::Ground,
                sim::indoor::IndoorTruthAt::Object(i) => TruthClass::Object(i),
                sim::indoor::IndoorTruthAt::Wall => TruthClass::Wall,
                sim::indoor::IndoorTruthAt::Nothing => TruthClass::Nothing,
            });
            (None, scores)
        }
    };
    let share = |v: Option<f64>| v.map_or_else(|| "-".to_string(), |v| format!("{v:.3}"));
    let log = |what: &str, score: &TruthScore| {
        tracing::info!(
            "against the truth ({}), {what}: voxels in agreement {}, ground navigable {}, object voxels in obstacles {}; \
             objects found {} of {} observed ({} split), obstacle precision {}; {} regions, the largest holds {} of the ground",
            path.display(),
            share(score.agreement),
            share(score.ground.share()),
            share(score.object.share()),
            score.objects_found,
            score.objects_observed,
            score.objects_split,
            share(score.precision),
            score.regions,
            share(score.largest_region_ground_share)
        )
    };
    log("each voxel where the map put it", &at_map);
    if let Some(l) = &at_map.landmarks {
        let rocks_and_wreck = rocks.map_or_else(String::new, |rocks| {
            let on = |rock: bool| l.per_object.iter().filter(move |o| (o.object < rocks) == rock);
            let on_rocks = on(true).map(|o| o.landmarks).max().unwrap_or(0);
            let on_wreck = on(false).map(|o| o.landmarks).sum::<usize>();
            format!("; at most {on_rocks} on one rock, {on_wreck} on the wreck")
        });
        tracing::info!(
            "obstacle landmarks seen in {} or more scans against the truth: {} of {} on objects; {} objects with one, {} with \
             several (at most {}{rocks_and_wreck})",
            l.min_scans,
            l.on_objects,
            l.landmarks,
            l.objects_with_one,
            l.objects_with_several,
            l.most_on_one_object
        );
    }
    if let Some(s) = &by_origin {
        log("each voxel where its points truly came from", s);
    }
    (Some(at_map), by_origin)
}

/// A simulated source's scene.json, as far as the truth needs it.
#[derive(serde::Deserialize)]
#[serde(untagged)]
enum SceneFile {
    /// The underwater simulator's: the scene under `scene`, next to the mission.
    Underwater { scene: Box<sim::scene::Scene> },
    /// The indoor simulator's boxes.
    Indoor { boxes: Vec<SceneBox> },
}

/// One box of the indoor scene.json.
#[derive(serde::Deserialize)]
struct SceneBox {
    min: [f64; 3],
    max: [f64; 3],
    what: String,
}

impl OctreeMapperStage {
    /// Takes the poses of the configured source into the pose buffer (the others are drained).
    fn take_poses(&mut self) -> Result<(), StageError> {
        let (source, poses) = (self.settings.pose_source, &mut self.st.poses);
        while let Some(s) = self.fused.receive()? {
            // The refined poses only: a predicted one (published at once, refined later) would
            // place clouds by an extrapolated buoy position.
            if source == PoseSource::Fused && s.payload().flags & shared_types::FUSED_PREDICTED == 0 {
                poses.push(s.user_header().stamp_ns as f64 / 1e9, s.payload().pose.frame_from_body());
            }
        }
        while let Some(s) = self.slam.receive()? {
            if source == PoseSource::Slam {
                poses.push(s.user_header().stamp_ns as f64 / 1e9, s.payload().frame_from_body());
            }
        }
        while let Some(s) = self.grid_slam.receive()? {
            if source == PoseSource::GridSlam {
                poses.push(s.user_header().stamp_ns as f64 / 1e9, s.payload().frame_from_body());
            }
        }
        Ok(())
    }

    /// Takes clouds while the state takes them (with `when_behind = "wait"` none while
    /// max_pending_clouds wait: the rest stays in the service's queue and a replay waits for the
    /// mapper); counts sequence gaps. Returns whether the service's queue is empty.
    fn take_clouds(&mut self) -> Result<bool, StageError> {
        let now = Instant::now();
        while self.st.takes_clouds() {
            let Some(s) = self.clouds.receive()? else { return Ok(true) };
            let h = s.user_header();
            self.last_stamp = self.last_stamp.max(h.msg.stamp_ns);
            // A publisher numbers its messages from 0: a first cloud with a later number means
            // the ones before it never reached this mapper (its queue overflowed before the first
            // wake-up, or it connected late). A restarted mapper starts mid-stream on purpose.
            let expected = match self.last_cloud_seq {
                Some(prev) => Some(prev + 1),
                None => (!self.restarted).then_some(0),
            };
            if let Some(expected) = expected
                && h.msg.seq > expected
            {
                self.st.counters.clouds_missed += h.msg.seq - expected;
                self.clouds.count_dropped("missed: sequence gap", h.msg.seq - expected);
            }
            self.last_cloud_seq = Some(h.msg.seq);
            let own_pose = (h.flags & CLOUD_HAS_POSE != 0)
                .then(|| convert::isometry_from_wire(&h.sensor_origin_m, &h.orientation_xyzw));
            self.st.push_cloud(PendingCloud {
                stamp_ns: h.msg.stamp_ns,
                origin_ns: h.msg.origin_ns,
                points_sensor_m: s.payload().iter().map(|p| [p.x_m, p.y_m, p.z_m]).collect(),
                own_pose,
                received: now,
            });
        }
        Ok(false)
    }

    /// Commands for this process (or everyone): a full voxel set, a checkpoint of `map.bt`.
    fn take_commands(&mut self, rt: &mut Runtime) -> Result<(), StageError> {
        while let Some(s) = self.commands.receive()? {
            let c = s.payload();
            let target = name_from32(&c.target);
            if (target.is_empty() || target == rt.name()) && c.command == COMMAND_VOXEL_SNAPSHOT {
                self.voxel_stream.request_snapshot();
            }
            if (target.is_empty() || target == rt.name()) && c.command == COMMAND_CHECKPOINT {
                let _alive = rt.hold_heartbeat(); // writing a large tree: seconds, not a hang
                let path = self.out_dir.join("map.bt");
                std::fs::create_dir_all(&self.out_dir)?;
                self.st.tree.write_binary_file(&path).map_err(StageError::stage)?;
                tracing::info!(path = %path.display(), "checkpoint written");
            }
        }
        Ok(())
    }

    /// What is due by the clock: the restart checkpoint, the map statistics, the voxel stream,
    /// the plane fits' refresh.
    fn periodic_outputs(&mut self, rt: &mut Runtime, inputs_ended: bool) -> Result<(), StageError> {
        if self.fits_every.is_some_and(|e| self.last_fits.elapsed() >= e) && !inputs_ended {
            self.last_fits = Instant::now();
            // Bounded work; its table of fits grows by rehashing at once, as the insertion's.
            let _alive = rt.hold_heartbeat();
            let fitted = self.st.refresh_fits();
            tracing::debug!(fitted, kept = self.st.fits.len(), "plane fits refreshed");
        }
        if self.traversability_every.is_some_and(|e| self.last_traversability.elapsed() >= e) && !inputs_ended {
            // The discovery of the map so far and its grid for a planner beside the mapper; the
            // insertion waits meanwhile (bounded work: the heartbeat goes on).
            let _alive = rt.hold_heartbeat();
            let t0 = Instant::now();
            let d = self.st.discover()?;
            let grid = navigable::traversability::TraversabilityGrid::from_discovery(&self.st.points, &d);
            send_traversability(&mut self.traversability_out, &grid, self.last_stamp)?;
            let (navigable, obstacle, unknown) = grid.counts();
            tracing::debug!(
                navigable,
                obstacle,
                unknown,
                ms = t0.elapsed().as_secs_f64() * 1e3,
                "traversability grid of the map so far sent"
            );
            // The period counts from the end of this one: a discovery longer than the period
            // does not run back to back.
            self.last_traversability = Instant::now();
        }
        if self.checkpoint_every.is_some_and(|e| self.last_checkpoint.elapsed() >= e) && !inputs_ended {
            self.last_checkpoint = Instant::now();
            // Serialising and writing the whole tree takes seconds on a large map on a loaded
            // machine: bounded work, not a hang, so the heartbeat goes on meanwhile.
            let _alive = rt.hold_heartbeat();
            let bytes = self.st.checkpoint()?;
            rt.state().snapshot(CHECKPOINT, &bytes)?;
            self.inserted_at_checkpoint = self.st.counters.clouds_inserted;
        }
        if self.stats_every.is_some_and(|e| self.last_stats.elapsed() >= e) {
            self.last_stats = Instant::now();
            let header = MsgHeader { stamp_ns: self.last_stamp, ..Default::default() };
            self.stats_out.send_value(header, stats_msg(&self.st, 0, 0))?;
        }
        if self.voxels_every.is_some_and(|e| self.last_voxels.elapsed() >= e) {
            self.last_voxels = Instant::now();
            let _alive = rt.hold_heartbeat(); // a full set walks the whole tree
            send_voxels(&mut self.voxels_out, &mut self.voxel_stream, &mut self.st, None, self.last_stamp)?;
        }
        Ok(())
    }
}

impl Stage for OctreeMapperStage {
    type Settings = MapperSettings;

    fn open(ctx: &ProcessContext, settings: MapperSettings, rt: &mut Runtime) -> Result<Self, StageError> {
        let st = MapperState::new(settings.clone())?;
        let checkpoint_every =
            (settings.checkpoint_interval_s > 0.0).then(|| Duration::from_secs_f64(settings.checkpoint_interval_s));
        let every = |hz: f64| (hz > 0.0).then(|| Duration::from_secs_f64(1.0 / hz));
        tracing::info!(resolution_m = settings.resolution_m, pose = ?settings.pose_source, "octree mapper ready");
        Ok(Self {
            st,
            checkpoint_every,
            last_checkpoint: Instant::now(),
            inserted_at_checkpoint: 0,
            clouds: rt.input(CLOUD)?,
            fused: rt.input(FUSION_POSE)?,
            slam: rt.input(SLAM_POSE)?,
            grid_slam: rt.input(GRID_SLAM_POSE3D)?,
            commands: rt.input(COMMAND)?,
            stats_out: rt.output(MAP_STATS)?,
            voxels_out: rt.output_slice(MAP_VOXELS, 16 * 1024)?,
            traversability_out: rt.output_slice(MAP_TRAVERSABILITY, 1024 * 1024)?,
            traversability_every: (settings.traversability_interval_s > 0.0)
                .then(|| Duration::from_secs_f64(settings.traversability_interval_s)),
            last_traversability: Instant::now(),
            voxel_stream: VoxelStream::new(
                crate::voxels::RegionGrid {
                    resolution_m: settings.resolution_m,
                    depth: crate::voxels::VOXEL_REGION_DEPTH,
                },
                (settings.voxels_full_interval_s > 0.0)
                    .then(|| Duration::from_secs_f64(settings.voxels_full_interval_s)),
            ),
            stats_every: every(settings.stats_rate_hz),
            voxels_every: every(settings.voxels_rate_hz),
            fits_every: (settings.fits_refresh_interval_s > 0.0)
                .then(|| Duration::from_secs_f64(settings.fits_refresh_interval_s)),
            last_stats: Instant::now(),
            last_voxels: Instant::now(),
            last_fits: Instant::now(),
            last_stamp: 0,
            last_cloud_seq: None,
            restarted: false,
            out_dir: ctx.out_dir.clone(),
            settings,
        })
    }

    fn end_after(&self) -> EndAfter {
        EndAfter::from_list(&self.settings.end_after)
    }

    fn tick(&self) -> Option<Duration> {
        Some(Duration::from_millis(100))
    }

    /// A restarted instance starts from the killed one's last occupancy checkpoint.
    fn restore(&mut self, restart: Restart) -> Result<usize, StageError> {
        self.restarted = true;
        if let Some(path) = restart.snapshots.get(CHECKPOINT)
            && self.st.restore_checkpoint(path)?
        {
            let (occupied, free) = self.st.tree.num_occupied_free_leaves();
            tracing::info!(occupied, free, "restarted: the map starts from the killed instance's last checkpoint");
            tracing::warn!(
                "restarted: the points' statistics of the killed instance are not in its checkpoint; the navigable \
                 space, obstacles and walls at the end come from the clouds inserted from now on"
            );
        }
        Ok(0)
    }

    fn step(&mut self, rt: &mut Runtime, _wake: Wake, inputs_ended: bool) -> Result<Step, StageError> {
        self.take_poses()?;
        let queue_empty = self.take_clouds()?;
        self.take_commands(rt)?;
        // One cloud per wake-up, so the inputs are drained (and late clouds dropped) between.
        let st = &mut self.st;
        let before = (st.counters.clouds_dropped_behind, st.counters.clouds_dropped_no_pose);
        // A cloud's insertion is bounded work, but when the voxels' statistics outgrow their
        // table it is rehashed at once (1-2 M voxels: seconds on a loaded machine, where the
        // main job's mapper was killed for a silent heartbeat, 2026-12-07): the heartbeat goes on
        // meanwhile, and an insertion that long is reported.
        let started = Instant::now();
        let alive = rt.hold_heartbeat();
        st.step(started, inputs_ended, 1)?;
        drop(alive);
        if started.elapsed() > SLOW_INSERTION {
            tracing::warn!(
                seconds = started.elapsed().as_secs_f64(),
                voxels = st.points.cells().len(),
                "a cloud's insertion took over {} s (the voxels' statistics table grew)",
                SLOW_INSERTION.as_secs_f64()
            );
        }
        self.clouds.count_dropped(
            "insertion behind (when_behind = drop_oldest)",
            st.counters.clouds_dropped_behind - before.0,
        );
        self.clouds.count_dropped("no pose within pose_wait_s", st.counters.clouds_dropped_no_pose - before.1);
        if !st.pending.is_empty() {
            match st.next_deadline() {
                Some(d) if st.settings().pose_source != PoseSource::Cloud => {
                    rt.wake_at(d.min(Instant::now() + Duration::from_millis(20)))
                }
                _ => rt.wake_at(Instant::now()),
            }
        } else if !queue_empty {
            rt.wake_at(Instant::now()); // clouds left in the service's queue: take them now
        }
        self.periodic_outputs(rt, inputs_ended)?;
        // Clouds waiting for their pose, and those inserted since the last checkpoint (a restarted
        // mapper starts from it): lost (and counted) if it is killed now.
        let since_checkpoint = self.st.counters.clouds_inserted - self.inserted_at_checkpoint;
        self.clouds.set_held(self.st.pending.len() as u64 + since_checkpoint);
        Ok(if queue_empty && self.st.pending.is_empty() { Step::Idle } else { Step::Pending })
    }

    type Summary = OctreeMapperPart;

    fn finish(&mut self, rt: &mut Runtime, ending: Ending) -> Result<Self::Summary, StageError> {
        let mut rebuild = None;
        if ending == Ending::EndOfStream && !self.settings.rebuild_from.is_empty() {
            let path = self.out_dir.join(&self.settings.rebuild_from);
            match geometry::tum::read_tum(&path) {
                Ok(_) if self.st.kept.is_empty() => tracing::warn!(
                    "no rebuild: no cloud kept (a restarted mapper has not the killed one's clouds): map.bt is the live map"
                ),
                Ok(traj) if !traj.is_empty() => {
                    std::fs::create_dir_all(&self.out_dir)?;
                    let alive = rt.hold_heartbeat();
                    self.st.tree.write_binary_file(self.out_dir.join("map_live.bt")).map_err(StageError::stage)?;
                    drop(alive);
                    let t0 = Instant::now();
                    let (st, name) = (&mut self.st, &self.settings.rebuild_from);
                    // Heartbeats go on while the clouds are re-inserted (seconds on a long run).
                    let r = std::thread::scope(|s| {
                        let worker = s.spawn(|| st.rebuild(&traj, name));
                        while !worker.is_finished() {
                            rt.keep_alive();
                            std::thread::sleep(Duration::from_millis(50));
                        }
                        worker.join().map_err(|_| StageError::msg("rebuild worker panicked"))
                    })??;
                    tracing::info!(
                        clouds = r.clouds,
                        without_pose = r.clouds_without_pose,
                        mean_pose_change_m = r.mean_pose_change_m,
                        "map rebuilt along {} in {:.1} s (the live map is map_live.bt)",
                        path.display(),
                        t0.elapsed().as_secs_f64()
                    );
                    if r.clouds_without_pose > 0 || r.clouds_not_kept > 0 {
                        tracing::warn!(
                            without_pose = r.clouds_without_pose,
                            not_kept = r.clouds_not_kept,
                            "clouds left out of the rebuilt map"
                        );
                    }
                    rebuild = Some(r);
                }
                Ok(_) => tracing::warn!("no rebuild: {} is empty", path.display()),
                Err(e) => tracing::warn!("no rebuild: {e}"),
            }
        }
        if ending == Ending::EndOfStream {
            let (d, voxels, grid, mut part) = end_of_run(rt, &self.st, &self.out_dir)?;
            send_traversability(&mut self.traversability_out, &grid, self.last_stamp)?;

            let header = MsgHeader { stamp_ns: self.last_stamp, ..Default::default() };
            self.stats_out.send_value(header, stats_msg(&self.st, d.regions.len() as u32, d.obstacles.len() as u32))?;
            let _alive = rt.hold_heartbeat();
            send_voxels(&mut self.voxels_out, &mut self.voxel_stream, &mut self.st, Some(voxels), self.last_stamp)?;
            if let Some(end) = part.octree_mapper.end_of_stream.as_mut() {
                end.rebuild = rebuild;
                end.voxel_stream = VoxelStreamSummary::from(&self.voxel_stream.counters);
            }
            return Ok(part);
        }
        let st = &self.st;
        // Stopped before the end of stream: the map so far (the navigable-space layers take
        // seconds on a large map and are written only at the end of stream).
        std::fs::create_dir_all(&self.out_dir)?;
        let alive = rt.hold_heartbeat();
        st.tree.write_binary_file(self.out_dir.join("map.bt")).map_err(StageError::stage)?;
        drop(alive);
        let (occ, free) = st.tree.num_occupied_free_leaves();
        tracing::info!(clouds = st.counters.clouds_inserted, "stopped early: map.bt written");
        Ok(OctreeMapperPart {
            octree_mapper: MapperSummary {
                resolution_m: st.tree.resolution(),
                stopped_early: true,
                pose_source: None,
                leaves: occ + free,
                occupied_leaves: occ,
                free_leaves: free,
                memory_bytes: None,
                counters: st.counters.clone(),
                end_of_stream: None,
            },
            pipeline_latency_ms: None,
        })
    }

    fn end_of_stream(&self) -> (u64, u64) {
        (self.stats_out.sent().saturating_sub(1), self.stats_out.sent())
    }
}
