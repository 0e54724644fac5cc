//! Room to watch (issue 17): every service of the shipped main job admits a viewer and a recorder
//! next to the pipeline's own consumers, and `run.extra_subscribers` makes room for more.
//!
//! The main job's process graph (config/default.toml, on a short mission) runs with two recorders
//! that subscribe to every service, clouds and voxels included, and start before the pipeline's
//! consumers (so they take their slots first, the worst case): every stage still opens its
//! inputs, the run ends cleanly and neither recorder misses a service. A third recorder does not
//! fit, says which key to raise, and with `run.extra_subscribers = 1` it does.

use std::path::PathBuf;
use std::time::Duration;

use pipeline_tests::TestRun;

const LONG: Duration = Duration::from_secs(300);

/// The `[processes.*]` tables of config/default.toml on a 45 s mission (10 particles; the depth camera sees the
/// bottom from about 25 s), with `recorders` (names)
/// added to ingest's `after`; they start before the pipeline's consumers (`first`) or after them.
fn default_graph_with(recorders: &[&str], first: bool) -> (String, Vec<String>) {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../config/default.toml");
    let text = std::fs::read_to_string(&path).expect("config/default.toml");
    let start = text.find("[processes.").expect("a process table");
    let mut procs = text[start..].to_string();
    let quoted: Vec<String> = recorders.iter().map(|r| format!("\"{r}\"")).collect();
    let after = r#"after = ["monitor", "slam", "buoy", "map"]"#;
    assert!(procs.contains(after), "ingest's `after` in config/default.toml changed: update this test");
    procs = procs.replace(after, &format!(r#"after = ["monitor", "slam", "buoy", "map", {}]"#, quoted.join(", ")));
    let sim = "[processes.ingest.settings.sim]\nseed = 1";
    assert!(procs.contains(sim), "ingest's sim table in config/default.toml changed: update this test");
    procs = procs.replace(sim, &format!("{sim}\n[processes.ingest.settings.sim.mission]\nmax_duration_s = 45.0"));
    // Fewer particles: these debug-built runs are about who subscribes, not about accuracy.
    let particles = "particles = 100";
    assert!(procs.contains(particles), "fastslam's particles in config/default.toml changed: update this test");
    procs = procs.replace(particles, "particles = 10");
    for r in recorders {
        procs.push_str(&format!(
            r#"
[processes.{r}]
kind = "recorder"
{}
[processes.{r}.settings]
file = "{r}.mcap"
end_after = ["ingest", "slam", "buoy", "sync", "fusion", "map"]
compression = "lz4"
"#,
            if first { "" } else { r#"after = ["monitor", "slam", "buoy", "sync", "fusion", "map"]"# }
        ));
    }
    // The recorders end after the producers (`end_after`) but send no end of stream of their own.
    let ends: Vec<String> =
        ["monitor", "slam", "buoy", "sync", "fusion", "map"].iter().map(|s| format!("\"{s}\"")).collect();
    (procs, ends)
}

#[test]
fn the_main_job_leaves_room_for_a_viewer_and_a_recorder_on_every_service() {
    let _heavy = pipeline_tests::heavy();
    let mut run = TestRun::new("watch");
    let (procs, ends) = default_graph_with(&["rec1", "rec2"], true);
    let s = run.run_to_end(
        &format!("end = \"end_of_stream\"\nend_of_stream_from = [{}]\nduration_s = 200", ends.join(", ")),
        &procs,
        LONG,
    );
    let log = run.log();
    assert!(!log.contains("ExceedsMaxSupportedSubscribers"), "{log}");
    use crate::summary_schema::part;
    let sup: supervisor::report::SupervisorPart = part(&s);
    for name in ["monitor", "slam", "buoy", "sync", "fusion", "map", "ingest", "rec1", "rec2"] {
        assert_eq!(sup.processes[name].state, "done", "{name}: {:?}", sup.processes[name]);
    }
    let recorders = part::<recorder_stage::summary::RecorderPart>(&s).recorders;
    for rec in ["rec1", "rec2"] {
        let r = &recorders[rec];
        assert!(r.not_recorded.is_empty(), "{rec}: {r:?}");
        for service in
            ["pipeline/sensors/cloud", "pipeline/map/voxels", "pipeline/fusion/pose", "pipeline/slam/landmarks"]
        {
            assert!(r.messages.get(service).is_some_and(|&n| n > 0), "{rec} recorded no {service}: {r:?}");
        }
        // Sensor data waits for every subscriber in a replay: the recorders lose none of it.
        assert_eq!(r.missed.get("pipeline/sensors/cloud"), Some(&0), "{rec}: {r:?}");
    }
    // The mapper inserted every cloud the recorders saw.
    let clouds = recorders["rec1"].messages["pipeline/sensors/cloud"];
    let mapper = part::<octree_mapper_stage::summary::OctreeMapperPart>(&s).octree_mapper;
    assert_eq!(mapper.counters.clouds_inserted, clouds, "{:#}", s["octree_mapper"]);

    // The recording opens in Foxglove: Python's mcap reader finds Foxglove's schemas next to the
    // raw channels and decodes a cloud, the poses and the octree with the schemas in the file.
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("python/mcap_foxglove.py");
    let out = std::process::Command::new("python3")
        .arg(&script)
        .arg(run.out_dir().join("rec1.mcap"))
        .output()
        .expect("python3 runs tests/python/mcap_foxglove.py");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let fox: serde_json::Value = serde_json::from_slice(&out.stdout).expect("its JSON");
    let rec = &recorders["rec1"];
    for (topic, schema, service) in [
        ("/cloud", "foxglove.PointCloud", "pipeline/sensors/cloud"),
        ("/fused/pose", "foxglove.PoseInFrame", "pipeline/fusion/pose"),
        ("/slam/pose", "foxglove.PoseInFrame", "pipeline/slam/pose"),
        ("/buoy/pose", "foxglove.PoseInFrame", "pipeline/buoy/fix"),
        ("/landmarks", "foxglove.PointCloud", "pipeline/fusion/map"),
    ] {
        assert_eq!(fox[topic]["schema"], schema, "{topic}: {fox:#}");
        // One Foxglove message per raw one, counted the same by the recorder and Python.
        assert_eq!(fox[topic]["count"], rec.messages[service], "{topic}: {fox:#}\n{rec:?}");
        assert_eq!(fox[topic]["count"], rec.foxglove_messages[topic], "{topic}: {rec:?}");
    }
    assert_eq!(fox["/fused/pose"]["last"]["finite"], true, "{fox:#}");
    assert_eq!(fox["/fused/pose"]["last"]["frame_id"], "world", "{fox:#}");
    assert!(fox["/cloud"]["last"]["points"].as_u64().unwrap_or(0) > 0, "{fox:#}");
    // The octree: its full voxel sets (not the deltas), with the voxels' fields.
    assert_eq!(fox["/octree"]["schema"], "foxglove.PointCloud", "{fox:#}");
    assert!(fox["/octree"]["last"]["points"].as_u64().unwrap_or(0) > 100, "{fox:#}");
    assert_eq!(fox["/octree"]["last"]["fields"][3], "occupancy", "{fox:#}");
}

#[test]
fn a_third_watcher_needs_extra_subscribers_and_says_so() {
    // Without room: the recorders, started after the pipeline's consumers, fill the cloud
    // service's two free slots and the third cannot tap it; it names the key to raise.
    let mut run = TestRun::new("watch3");
    let (procs, ends) = default_graph_with(&["rec1", "rec2", "rec3"], false);
    let run_extra = format!("end = \"end_of_stream\"\nend_of_stream_from = [{}]\nduration_s = 200", ends.join(", "));
    let s = run.run_to_end(&run_extra, &procs, LONG);
    // Which of the three lost the race for the last slot depends on start-up order.
    use crate::summary_schema::part;
    let recorders = part::<recorder_stage::summary::RecorderPart>(&s).recorders;
    let losers: Vec<&String> =
        recorders.values().filter_map(|r| r.not_recorded.get("pipeline/sensors/cloud")).collect();
    assert_eq!(losers.len(), 1, "one recorder without the clouds: {losers:?}");
    assert!(losers[0].contains("run.extra_subscribers"), "{}", losers[0]);
    // The pipeline's own consumers started after the recorders and still got their inputs.
    let sup: supervisor::report::SupervisorPart = part(&s);
    for name in ["monitor", "slam", "buoy", "sync", "fusion", "map", "ingest"] {
        assert_eq!(sup.processes[name].state, "done", "{name}: {:?}", sup.processes[name]);
    }

    // With one extra subscriber per service all three record everything.
    let mut run = TestRun::new("watch3x");
    let s = run.run_to_end(&format!("{run_extra}\nextra_subscribers = 1"), &procs, LONG);
    let recorders = part::<recorder_stage::summary::RecorderPart>(&s).recorders;
    for rec in ["rec1", "rec2", "rec3"] {
        assert!(recorders[rec].not_recorded.is_empty(), "{rec}: {:?}", recorders[rec]);
    }
    assert_eq!(part::<supervisor::report::SupervisorPart>(&s).processes["map"].state, "done");
}
