//! Every stage of the main job through its `Stage` implementation, without iceoryx2: each is
//! opened on in-process queues (`pipeline_runtime::testing::StageHarness`) with its settings
//! from config/default.toml (the mission cut to 30 s), and this test carries the messages
//! between them the way the services would, wakes them in turn, and sends each one's end of
//! stream to its consumers. It checks what each stage published, its end of stream, its summary
//! part, and the scores it computed against the simulator's ground truth.

use std::path::Path;
use std::time::Duration;

use buoy_ekf_stage::stage::BuoyEkfStage;
use fastslam_stage::stage::FastSlamStage;
use fusion_stage::stage::FusionStage;
use ingest_stage::stage::IngestStage;
use octree_mapper_stage::stage::OctreeMapperStage;
use pipeline_runtime::testing::StageHarness;
use pipeline_runtime::{Stage, Step};
use shared_types::services::*;
use shared_types::*;
use synchronizer_stage::stage::SynchronizerStage;

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
    StageHarness::<S>::from_config_str(config, &source, name, out)
}

/// True once `h` has finished (its summary part is written).
fn ended<S: Stage>(h: &StageHarness<S>) -> bool {
    h.summary().is_some()
}

#[test]
fn the_main_job_runs_stage_by_stage_in_one_process() -> anyhow::Result<()> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let mut config = std::fs::read_to_string(root.join("config/default.toml"))?;
    config.push_str("\n[processes.ingest.settings.sim.mission]\nmax_duration_s = 30.0\n");
    let dir = tempfile::tempdir()?;
    let out = dir.path();

    let mut ingest = open::<IngestStage>(&config, "ingest", out)?;
    let mut slam = open::<FastSlamStage>(&config, "slam", out)?;
    let mut buoy = open::<BuoyEkfStage>(&config, "buoy", out)?;
    let mut sync = open::<SynchronizerStage>(&config, "sync", out)?;
    let mut fusion = open::<FusionStage>(&config, "fusion", out)?;
    let mut map = open::<OctreeMapperStage>(&config, "map", out)?;

    let (mut clouds, mut stereo, mut fixes, mut poses, mut pairs, mut fused) = (0, 0, 0, 0, 0, 0);
    let mut source_done = false;
    let mut rounds = 0;
    // Data flows downstream each round; a stage's end of stream goes to its consumers once it
    // has finished, after its last data.
    while !ended(&map) {
        rounds += 1;
        anyhow::ensure!(rounds < 200_000, "the pipeline has not ended after {rounds} rounds");
        if !source_done {
            // A source publishes one item per wake (Busy) until Done.
            for _ in 0..20 {
                if matches!(ingest.wake()?, Some(Step::Done) | None) {
                    source_done = true;
                    break;
                }
            }
        }
        pipe!(ingest, ODOMETRY, OdometryInput, MsgHeader => slam, buoy);
        stereo += pipe_slices!(ingest, STEREO, StereoObservation, MsgHeader => slam);
        pipe_slices!(ingest, BUOY_RANGES, BuoyRange, MsgHeader => buoy);
        pipe!(ingest, DEPTH, DepthReading, MsgHeader => buoy);
        pipe!(ingest, HEADING, HeadingReading, MsgHeader => fusion);
        clouds += pipe_slices!(ingest, CLOUD, CloudPoint, CloudHeader => map);
        if ingest.end_of_stream()?.is_some() {
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
                sync.end_upstream(name)?;
                fusion.end_upstream(name)?;
            }
        }

        sync.wake()?;
        pairs += pipe!(sync, SYNC_PAIR, SyncedPair, MsgHeader => fusion);
        if sync.end_of_stream()?.is_some() {
            fusion.end_upstream("sync")?;
        }
        fusion.wake()?;
        fused += pipe!(fusion, FUSION_POSE, FusedPose, MsgHeader => map);
        pipe!(fusion, COMMAND, ControlCommand, MsgHeader => slam, map);
        fusion.take_slices::<Landmark, LandmarkMapHeader>(FUSION_MAP)?;
        if fusion.end_of_stream()?.is_some() {
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

    // What flowed: every stage published, nothing was left behind.
    assert!(clouds >= 10 && stereo >= 300, "ingest published {clouds} clouds and {stereo} stereo frames");
    assert!(fixes >= 15, "{fixes} buoy fixes in 30 s at 1 Hz");
    assert_eq!(poses, stereo, "one SLAM pose per stereo frame");
    assert_eq!(pairs, poses, "the synchronizer pairs every SLAM pose");
    assert_eq!(fused, pairs, "fusion publishes a pose per pair");

    // Each stage's summary part, as the process writes it for the supervisor.
    let part = |name: &str| -> anyhow::Result<serde_json::Value> {
        Ok(serde_json::from_slice(&std::fs::read(out.join("parts").join(format!("{name}.json")))?)?)
    };
    let ingest_part = part("ingest")?;
    assert_eq!(ingest_part["ingest"]["completed"], true, "{ingest_part}");
    let map_part = part("map")?;
    assert_eq!(map_part["octree_mapper"]["counters"]["clouds_inserted"].as_u64(), Some(clouds), "{map_part}");
    let sync_part = part("sync")?;
    assert_eq!(sync_part["synchronizer"]["pairs"].as_u64(), Some(pairs), "{sync_part}");

    // Scores against the ground truth the ingest stage wrote (30 s of the mission: a short
    // drive, so the bounds are loose; the full mission's numbers are in the README).
    let ate = |p: &serde_json::Value, k: &str| p["ate_m"][k].as_f64().unwrap_or(f64::NAN);
    let buoy_ate = ate(&part("buoy")?, "buoy_ekf");
    let slam_ate = ate(&part("slam")?, "slam");
    let fused_ate = ate(&part("fusion")?, "fused");
    println!("30 s in one process: ATE buoy {buoy_ate:.3} m, SLAM {slam_ate:.3} m, fused {fused_ate:.3} m");
    assert!(buoy_ate < 1.0, "buoy ATE {buoy_ate}");
    assert!(slam_ate < 1.0, "SLAM ATE {slam_ate}");
    assert!(fused_ate < 1.0, "fused ATE {fused_ate}");
    assert!(out.join("map.bt").is_file(), "the mapper wrote map.bt");
    Ok(())
}
