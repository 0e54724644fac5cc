//! Every stage of the main job through its `Stage` implementation, without iceoryx2: each is
//! opened on in-process queues (`pipeline_runtime::testing::StageHarness`) with its settings
//! from config/default.toml (the mission cut to 30 s), and this test carries the messages
//! between them the way the services would, wakes them in turn, and sends each one's end of
//! stream to its consumers. It checks what each stage published, its end of stream, its summary
//! part, and the scores it computed against the simulator's ground truth.

use std::path::Path;
use std::time::Duration;

use buoy_ekf_stage::stage::BuoyEkfStage;
use buoy_ekf_stage::summary::BuoyEkfPart;
use fastslam_stage::stage::FastSlamStage;
use fastslam_stage::summary::FastSlamPart;
use fusion_stage::stage::FusionStage;
use fusion_stage::summary::FusionPart;
use ingest_stage::stage::IngestStage;
use ingest_stage::summary::IngestPart;
use octree_mapper_stage::stage::OctreeMapperStage;
use octree_mapper_stage::summary::OctreeMapperPart;
use pipeline_runtime::testing::StageHarness;
use pipeline_runtime::{Stage, Step};
use shared_types::services::*;
use shared_types::*;
use synchronizer_stage::stage::SynchronizerStage;
use synchronizer_stage::summary::SynchronizerPart;

/// Moves what `$from` published on `$svc` to every `$to` (fixed-size messages); returns the count.
macro_rules! pipe {
    ($from:expr, $svc:expr, $t:ty, $h:ty => $($to:expr),+) => {{
        let msgs = $from.take::<$t, $h>($svc)?;
        for (h, v) in &msgs {
            $( $to.feed::<$t, $h>($svc, *h, *v)?; )+
        }
        msgs.len() as u64
    }};
}

/// As `pipe!` for slice messages.
macro_rules! pipe_slices {
    ($from:expr, $svc:expr, $t:ty, $h:ty => $($to:expr),+) => {{
        let msgs = $from.take_slices::<$t, $h>($svc)?;
        for (h, v) in &msgs {
            $( $to.feed_slice::<$t, $h>($svc, *h, v)?; )+
        }
        msgs.len() as u64
    }};
}

fn open<S: Stage>(config: &str, name: &str, out: &Path) -> anyhow::Result<StageHarness<S>> {
    let source = Path::new(env!("CARGO_MANIFEST_DIR")).join("../config/default.toml");
    Ok(StageHarness::<S>::from_config_str(config, &source, name, out)?)
}

/// True once `h` has finished (its summary part is written).
fn ended<S: Stage>(h: &StageHarness<S>) -> bool {
    h.summary().is_some()
}

/// Messages carried between the stages.
#[derive(Debug, Default)]
struct Flow {
    clouds: u64,
    stereo: u64,
    fixes: u64,
    poses: u64,
    pairs: u64,
    fused: u64,
    /// The stages restarted.
    restarted: Vec<&'static str>,
    /// Stereo frames the restarted SLAM counted as lost in the restart (they sat in the killed
    /// instance's queue).
    slam_stereo_lost: u64,
}

/// Runs the main job's stages on a 30 s mission into `out`; with `restart_at`, every stage is
/// killed and restarted (as the supervisor would) once that many stereo frames were published,
/// the source then replaying at 10x real time (so that the kill comes mid-stream, not after a
/// source that has published everything at once).
fn run_chain(out: &Path, restart_at: Option<u64>) -> anyhow::Result<Flow> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let mut config = std::fs::read_to_string(root.join("config/default.toml"))?;
    config.push_str("\n[processes.ingest.settings.sim.mission]\nmax_duration_s = 30.0\n");
    if restart_at.is_some() {
        anyhow::ensure!(config.contains("real_time_factor = 0.0"), "config/default.toml: no real_time_factor");
        config = config.replace("real_time_factor = 0.0", "real_time_factor = 10.0");
    }

    let mut ingest = open::<IngestStage>(&config, "ingest", out)?;
    let mut slam = open::<FastSlamStage>(&config, "slam", out)?;
    let mut buoy = open::<BuoyEkfStage>(&config, "buoy", out)?;
    let mut sync = open::<SynchronizerStage>(&config, "sync", out)?;
    let mut fusion = open::<FusionStage>(&config, "fusion", out)?;
    let mut map = open::<OctreeMapperStage>(&config, "map", out)?;

    let (mut clouds, mut stereo, mut fixes, mut poses, mut pairs, mut fused) = (0, 0, 0, 0, 0, 0);
    let mut source_done = false;
    let mut rounds = 0;
    let mut restart_at = restart_at;
    let mut eos_seen: Vec<&str> = vec![];
    let mut restarted: Vec<&str> = vec![];
    // Data flows downstream each round; a stage's end of stream goes to its consumers once it
    // has finished, after its last data.
    while !ended(&map) {
        rounds += 1;
        anyhow::ensure!(
            rounds < 200_000,
            "the pipeline has not ended after {rounds} rounds: ended ingest {} slam {} buoy {} sync {} fusion {} map {}",
            ended(&ingest),
            ended(&slam),
            ended(&buoy),
            ended(&sync),
            ended(&fusion),
            ended(&map)
        );
        if !source_done {
            // A source publishes one item per wake (Busy) until Done.
            for _ in 0..20 {
                if restart_at.is_some() || restarted.contains(&"ingest") {
                    std::thread::sleep(Duration::from_micros(200)); // wall time for the paced source
                }
                if matches!(ingest.wake()?, Some(Step::Done) | None) {
                    source_done = true;
                    break;
                }
            }
        }
        if restart_at.is_some_and(|n| stereo >= n) {
            // Kill -9 and restart of every stage still running: what sits in their queues is
            // lost, what they kept through the runtime (journals, snapshots) is restored, and
            // the ends of stream they had seen are sent again (as the supervisor does).
            restart_at = None;
            macro_rules! restart {
                ($h:ident, $name:expr) => {
                    if !ended(&$h) {
                        $h = $h.restart()?;
                        for from in &eos_seen {
                            $h.end_upstream(from)?;
                        }
                        restarted.push($name);
                    }
                };
            }
            restart!(ingest, "ingest");
            if restarted.contains(&"ingest") {
                source_done = false;
            }
            restart!(slam, "slam");
            restart!(buoy, "buoy");
            restart!(sync, "sync");
            restart!(fusion, "fusion");
            restart!(map, "map");
        }
        pipe!(ingest, ODOMETRY, OdometryInput, MsgHeader => slam, buoy);
        stereo += pipe_slices!(ingest, STEREO, StereoObservation, MsgHeader => slam);
        pipe_slices!(ingest, BUOY_RANGES, BuoyRange, MsgHeader => buoy);
        pipe!(ingest, DEPTH, DepthReading, MsgHeader => buoy);
        pipe!(ingest, HEADING, HeadingReading, MsgHeader => fusion);
        clouds += pipe_slices!(ingest, CLOUD, CloudPoint, CloudHeader => map);
        if ingest.end_of_stream()?.is_some() {
            eos_seen.push("ingest");
            slam.end_upstream("ingest")?;
            buoy.end_upstream("ingest")?;
            map.end_upstream("ingest")?;
        }

        buoy.wake()?;
        fixes += pipe!(buoy, BUOY_FIX, BuoyFix, MsgHeader => sync, fusion);
        slam.wake()?;
        poses += pipe!(slam, SLAM_POSE, PoseEstimate, MsgHeader => sync, map);
        pipe_slices!(slam, SLAM_LANDMARKS, Landmark, LandmarkMapHeader => fusion);
        slam.take_slices::<Particle, ParticleSetHeader>(SLAM_PARTICLES)?;
        slam.take::<SlamDiagnostics, MsgHeader>(SLAM_DIAGNOSTICS)?;
        for (h, name) in [(buoy.end_of_stream()?, "buoy"), (slam.end_of_stream()?, "slam")] {
            if h.is_some() {
                eos_seen.push(name);
                sync.end_upstream(name)?;
                fusion.end_upstream(name)?;
            }
        }

        sync.wake()?;
        pairs += pipe!(sync, SYNC_PAIR, SyncedPair, MsgHeader => fusion);
        if sync.end_of_stream()?.is_some() {
            eos_seen.push("sync");
            fusion.end_upstream("sync")?;
        }
        fusion.wake()?;
        fused += pipe!(fusion, FUSION_POSE, FusedPose, MsgHeader => map);
        pipe!(fusion, COMMAND, ControlCommand, MsgHeader => slam, map);
        fusion.take_slices::<Landmark, LandmarkMapHeader>(FUSION_MAP)?;
        if fusion.end_of_stream()?.is_some() {
            eos_seen.push("fusion");
            map.end_upstream("fusion")?;
        }
        map.wake()?;
        map.take::<MapStats, MsgHeader>(MAP_STATS)?;
        map.take_slices::<Voxel, VoxelSetHeader>(MAP_VOXELS)?;
        if ended(&ingest) && ended(&slam) && ended(&buoy) && ended(&sync) && ended(&fusion) && !ended(&map) {
            // Everything upstream is over: let the mapper finish its queue and its end-of-run work.
            map.run_to_end(Duration::from_secs(300))?;
        }
    }
    let report = slam.runtime().stats_report();
    let slam_stereo_lost = report
        .ports
        .iter()
        .filter(|p| p.input && p.service == STEREO)
        .flat_map(|p| p.dropped_by.iter())
        .filter(|(r, _)| r == pipeline_runtime::stats::LOST_IN_RESTART)
        .map(|(_, n)| *n)
        .sum();
    Ok(Flow { clouds, stereo, fixes, poses, pairs, fused, restarted, slam_stereo_lost })
}

/// The part file process `name` wrote (`parts/<name>.json`), read as its stage's summary struct.
fn part<T: serde::de::DeserializeOwned>(out: &Path, name: &str) -> anyhow::Result<T> {
    let path = out.join("parts").join(format!("{name}.json"));
    let value: serde_json::Value = serde_json::from_slice(&std::fs::read(&path)?)?;
    let undeclared = crate::summary_schema::undeclared(&crate::summary_schema::schema(), &value);
    assert!(undeclared.is_empty(), "{}: keys not in the schema: {undeclared:#?}", path.display());
    serde_json::from_value(value).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))
}

/// The buoy EKF's, SLAM's and the fused ATE (m; NaN when a part has none).
fn ates(out: &Path) -> anyhow::Result<[f64; 3]> {
    let buoy: BuoyEkfPart = part(out, "buoy")?;
    let slam: FastSlamPart = part(out, "slam")?;
    let fusion: FusionPart = part(out, "fusion")?;
    Ok([buoy.ate_m.and_then(|a| a.buoy_ekf), slam.ate_m.and_then(|a| a.slam), fusion.ate_m.and_then(|a| a.fused)]
        .map(|v| v.unwrap_or(f64::NAN)))
}

#[test]
fn the_main_job_runs_stage_by_stage_in_one_process() -> anyhow::Result<()> {
    let dir = tempfile::tempdir()?;
    let out = dir.path();
    let Flow { clouds, stereo, fixes, poses, pairs, fused, .. } = run_chain(out, None)?;

    // What flowed: every stage published, nothing was left behind.
    assert!(clouds >= 10 && stereo >= 300, "ingest published {clouds} clouds and {stereo} stereo frames");
    assert!(fixes >= 15, "{fixes} buoy fixes in 30 s at 1 Hz");
    assert_eq!(poses, stereo, "one SLAM pose per stereo frame");
    // Every SLAM pose is paired; those that waited for their fix were also predicted at once.
    let sync_part: SynchronizerPart = part(out, "sync")?;
    let predicted = sync_part.synchronizer.poses.predicted;
    assert_eq!(pairs, poses + predicted, "the synchronizer pairs every SLAM pose: {sync_part:?}");
    assert_eq!(fused, pairs, "fusion publishes a pose per pair, predicted or refined");

    // Each stage's summary part, as the process writes it for the supervisor.
    let ingest_part: IngestPart = part(out, "ingest")?;
    assert!(ingest_part.ingest.completed, "{ingest_part:?}");
    let map_part: OctreeMapperPart = part(out, "map")?;
    assert_eq!(map_part.octree_mapper.counters.clouds_inserted, clouds, "{map_part:?}");
    assert_eq!(sync_part.synchronizer.pairs, poses, "pairs proper: {sync_part:?}");
    let fusion_part: FusionPart = part(out, "fusion")?;
    assert_eq!(fusion_part.fusion.predicted as u64, predicted, "{fusion_part:?}");

    // Scores against the ground truth the ingest stage wrote (30 s of the mission: a short
    // drive, so the bounds are loose; the full mission's numbers are in docs/).
    let [buoy_ate, slam_ate, fused_ate] = ates(out)?;
    println!("30 s in one process: ATE buoy {buoy_ate:.3} m, SLAM {slam_ate:.3} m, fused {fused_ate:.3} m");
    assert!(buoy_ate < 1.0, "buoy ATE {buoy_ate}");
    assert!(slam_ate < 1.0, "SLAM ATE {slam_ate}");
    assert!(fused_ate < 1.0, "fused ATE {fused_ate}");
    assert!(out.join("map.bt").is_file(), "the mapper wrote map.bt");
    Ok(())
}

#[test]
fn every_stage_killed_and_restarted_mid_run_keeps_what_it_had() -> anyhow::Result<()> {
    let dir = tempfile::tempdir()?;
    let out = dir.path();
    let flow = run_chain(out, Some(200))?;
    println!("restarted after 200 stereo frames: {flow:?}");
    for name in ["slam", "buoy", "sync", "fusion", "map"] {
        assert!(flow.restarted.contains(&name), "{name} was not running any more at the restart: {flow:?}");
    }
    let slam: FastSlamPart = part(out, "slam")?;
    assert_eq!(slam.slam.segments, 2, "the restarted fastslam went on in a new local map: {slam:?}");
    // What sat in the killed SLAM's queue is counted as lost by the restarted one: every stereo
    // frame is either a pose or counted.
    assert_eq!(flow.stereo, flow.poses + flow.slam_stereo_lost, "{flow:?}");
    // The restarted ingest went on after what it had published: nothing twice.
    let ingest: IngestPart = part(out, "ingest")?;
    assert!(ingest.ingest.completed, "{ingest:?}");
    assert!(flow.stereo >= 300, "{flow:?}");
    // The trajectories cover the whole mission, not only the part after the restart: the
    // restarted stages kept what the killed ones had (journals), and the mapper its map.
    let truth = geometry::tum::read_tum(&out.join("ground_truth.tum"))?;
    let (t0, t1) = (truth[0].0, truth[truth.len() - 1].0);
    for f in ["slam_local.tum", "buoy_ekf.tum", "fused_live.tum"] {
        let rows = geometry::tum::read_tum(&out.join(f))?;
        let (a, b) = (rows[0].0, rows[rows.len() - 1].0);
        // (The buoy EKF starts at the first instant with four good ranges and a depth reading:
        // 1-2 s into this mission, whose vehicle is under way from the start.)
        assert!(a - t0 <= 2.5 && t1 - b < 2.0, "{f} covers {a:.1}..{b:.1} s of {t0:.1}..{t1:.1} s");
    }
    // Accuracy where each has estimates: what sat in the killed stages' queues is lost (as in a
    // kill -9), so the trajectories have a gap whose length depends on how far behind the
    // stages were (the machine's load); the ATE over every ground-truth row (the summary's)
    // counts that gap, this does not. The restarted buoy EKF went on from the killed one's
    // filter, so its fixes after the restart, and the fused poses aligned with them, are as good
    // as before.
    let truth_p: Vec<(f64, nalgebra::Vector3<f64>)> = truth.iter().map(|(t, p)| (*t, p.translation.vector)).collect();
    for (f, bound) in [("buoy_ekf.tum", 1.0), ("fused_global.tum", 1.0)] {
        let rows = geometry::tum::read_tum(&out.join(f))?;
        let est: Vec<_> = rows.iter().map(|(t, p)| (*t, p.translation.vector)).collect();
        let rms = geometry::trajectory::ate_nearest(&truth_p, &est, false); // over the estimate's rows
        let gap = rows.windows(2).map(|w| w[1].0 - w[0].0).fold(0.0, f64::max);
        println!(
            "after a restart of every stage: {f} RMS error {rms:.3} m at its {} rows, longest gap {gap:.1} s",
            rows.len()
        );
        assert!(rms < bound, "{f}: RMS error {rms} m");
    }
    for (key, v) in ["buoy_ekf", "slam", "fused"].into_iter().zip(ates(out)?) {
        println!("after a restart of every stage: ATE {key} {v:.3} m (every ground-truth row)");
        assert!(v.is_finite(), "{key}: ATE {v} m");
    }
    // SLAM's (each local map aligned to the truth on its own: no gap counted across two maps).
    assert!(ates(out)?[1] < 0.5, "SLAM ATE {} m", ates(out)?[1]);
    let map: OctreeMapperPart = part(out, "map")?;
    let inserted = map.octree_mapper.counters.clouds_inserted;
    assert!(
        inserted + 3 >= flow.clouds && inserted > 0,
        "{inserted} of {} clouds after the restart: {map:?}",
        flow.clouds
    );
    assert!(out.join("state/map/map.bt").is_file() || inserted > 0);
    Ok(())
}
