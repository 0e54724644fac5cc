//! The octree_mapper stage fed through `pipeline_runtime::testing::StageHarness` (no iceoryx2):
//! clouds that never reached the mapper are counted, also when they are the stream's first, and
//! so are those a restart lost.

use std::time::Duration;

use octree_mapper_stage::stage::OctreeMapperStage;
use pipeline_runtime::testing::StageHarness;
use shared_types::services::CLOUD;
use shared_types::{CLOUD_HAS_POSE, CloudHeader, CloudPoint, MsgHeader};

const CONFIG: &str = r#"
[run]
out_dir = "out"
[processes.map]
kind = "octree_mapper"
[processes.map.settings]
resolution_m = 0.2
pose_source = "cloud"
end_after = ["ingest"]
"#;

/// A cloud of a small wall 3 m ahead, taken at the origin at `t_s`.
fn cloud(t_s: f64) -> (CloudHeader, Vec<CloudPoint>) {
    let header = CloudHeader {
        msg: MsgHeader { stamp_ns: (t_s * 1e9) as u64, ..Default::default() },
        sensor_origin_m: [0.0; 3],
        orientation_xyzw: [0.0, 0.0, 0.0, 1.0],
        flags: CLOUD_HAS_POSE,
        ..Default::default()
    };
    let points = (0..20)
        .flat_map(|i| (0..10).map(move |j| CloudPoint { x_m: 3.0, y_m: -1.0 + 0.1 * i as f32, z_m: 0.1 * j as f32 }))
        .collect();
    (header, points)
}

fn counters(summary: &serde_json::Value) -> (u64, u64) {
    let c = &summary["octree_mapper"]["counters"];
    (c["clouds_inserted"].as_u64().unwrap(), c["clouds_missed"].as_u64().unwrap())
}

#[test]
fn clouds_lost_before_the_first_and_between_are_counted_as_missed() {
    let dir = tempfile::tempdir().unwrap();
    let mut map: StageHarness<OctreeMapperStage> =
        StageHarness::from_config_str(CONFIG, &dir.path().join("config.toml"), "map", dir.path()).unwrap();
    // The stream's first two clouds never arrive (the mapper connected late, or its queue
    // overflowed before its first wake-up), then one of the next four.
    map.lose(CLOUD, 2);
    for (i, t) in [0.2, 0.3, 0.4, 0.5].into_iter().enumerate() {
        if i == 2 {
            map.lose(CLOUD, 1);
        }
        let (h, points) = cloud(t);
        map.feed_slice(CLOUD, h, &points).unwrap();
        map.wake().unwrap();
    }
    map.end_upstream("ingest").unwrap();
    let summary = map.run_to_end(Duration::from_secs(60)).unwrap();
    assert_eq!(counters(&summary), (4, 3), "4 inserted, 2 + 1 missed: {:#}", summary["octree_mapper"]["counters"]);
    let stats = map.runtime().stats_report();
    assert!(format!("{stats:?}").contains("missed: sequence gap"), "{stats:?}");
}

#[test]
fn a_stream_that_arrives_whole_misses_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let mut map: StageHarness<OctreeMapperStage> =
        StageHarness::from_config_str(CONFIG, &dir.path().join("config.toml"), "map", dir.path()).unwrap();
    for t in [0.2, 0.3, 0.4] {
        let (h, points) = cloud(t);
        map.feed_slice(CLOUD, h, &points).unwrap();
    }
    map.end_upstream("ingest").unwrap();
    let summary = map.run_to_end(Duration::from_secs(60)).unwrap();
    assert_eq!(counters(&summary), (3, 0), "{:#}", summary["octree_mapper"]["counters"]);
}

/// Clouds the killed mapper received, `(queued, inserted since its last checkpoint)`, then lost
/// counted by the restarted one, with checkpoints every `checkpoint_interval_s`.
fn lost_in_restart(checkpoint_interval_s: f64) -> u64 {
    let dir = tempfile::tempdir().unwrap();
    let config = format!("{CONFIG}checkpoint_interval_s = {checkpoint_interval_s}\n");
    let mut map: StageHarness<OctreeMapperStage> =
        StageHarness::from_config_str(&config, &dir.path().join("config.toml"), "map", dir.path()).unwrap();
    for t in [0.2, 0.3, 0.4] {
        let (h, points) = cloud(t);
        map.feed_slice(CLOUD, h, &points).unwrap();
        map.wake().unwrap();
    }
    // A checkpoint is written on a wake-up once the interval has passed.
    std::thread::sleep(Duration::from_millis(30));
    map.wake().unwrap();
    let (h, points) = cloud(0.5);
    map.feed_slice(CLOUD, h, &points).unwrap(); // queued when it is killed
    let mut map = map.restart().unwrap();
    let (h, points) = cloud(0.6);
    map.feed_slice(CLOUD, h, &points).unwrap();
    map.wake().unwrap();
    let report = map.runtime().stats_report();
    let port = report.ports.iter().find(|p| p.input && p.service == CLOUD).expect("the cloud input");
    port.dropped_by.iter().find(|(r, _)| r == pipeline_runtime::stats::LOST_IN_RESTART).map_or(0, |(_, n)| *n)
}

#[test]
fn a_restarted_mapper_counts_the_clouds_its_map_lost() {
    // No checkpoint within the test: the restarted map lacks the three inserted clouds and the
    // queued one.
    assert_eq!(lost_in_restart(60.0), 4);
    // A checkpoint after the three: only the queued one is lost.
    assert_eq!(lost_in_restart(0.01), 1);
}
