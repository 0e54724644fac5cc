//! The live view (issue 17): the main job's graph (config/default.toml on a short mission) with a
//! `viewer` process; a real client of the `foxglove.websocket.v1` protocol
//! (tests/python/foxglove_ws_client.py, Python `websockets` + `protobuf`, decoding with the
//! schemas the server advertises, as the Foxglove app does) connects while the run goes on,
//! subscribes to every channel and decodes the trajectories (ground truth included), the live pose, the cloud, the
//! landmarks, the octree and the process states. The pipeline loses nothing to the viewer: the
//! mapper inserts every cloud, and the viewer saw every one.

use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::Duration;

use pipeline_tests::TestRun;

const LONG: Duration = Duration::from_secs(300);

/// The `[processes.*]` tables of config/default.toml on a 30 s mission at 4x real time with 10
/// particles (these debug-built runs are about the view, not accuracy), a viewer on `port`,
/// started before ingest.
fn default_graph_with_viewer(port: u16) -> String {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../config/default.toml");
    let text = std::fs::read_to_string(&path).expect("config/default.toml");
    let start = text.find("[processes.").expect("a process table");
    let mut procs = text[start..].to_string();
    let after = r#"after = ["monitor", "slam", "buoy", "map"]"#;
    assert!(procs.contains(after), "ingest's `after` in config/default.toml changed: update this test");
    procs = procs.replace(after, r#"after = ["monitor", "slam", "buoy", "map", "view"]"#);
    let sim = "[processes.ingest.settings.sim]\nseed = 1";
    assert!(procs.contains(sim), "ingest's sim table in config/default.toml changed: update this test");
    procs = procs.replace(sim, &format!("{sim}\n[processes.ingest.settings.sim.mission]\nmax_duration_s = 30.0"));
    // Paced at 4x real time, as a live robot would be (a few seconds for the client to join).
    let pace = "real_time_factor = 0.0";
    assert!(procs.contains(pace), "ingest's real_time_factor in config/default.toml changed: update this test");
    procs = procs.replace(pace, "real_time_factor = 4.0");
    let particles = "particles = 100";
    assert!(procs.contains(particles), "fastslam's particles in config/default.toml changed: update this test");
    procs = procs.replace(particles, "particles = 10");
    // Voxels twice a second, a full set every second: the client sees both kinds.
    let map = "[processes.map.settings]\n";
    assert!(procs.contains(map), "the mapper's settings table in config/default.toml changed: update this test");
    procs = procs.replace(map, &format!("{map}voxels_rate_hz = 2.0\nvoxels_full_interval_s = 1.0\n"));
    // A small backlog per client, clouds at their full rate: a client that stops reading soon
    // fills its outbox.
    procs.push_str(&format!(
        "\n[processes.view]\nkind = \"viewer\"\n[processes.view.settings]\nport = {port}\nclient_backlog = 4\ncloud_max_hz = 100.0\n"
    ));
    procs
}

#[test]
fn a_foxglove_client_follows_the_main_job_live_and_the_pipeline_loses_nothing() {
    let _heavy = pipeline_tests::heavy();
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let mut run = TestRun::new("view");
    let ends = r#"end = "end_of_stream"
end_of_stream_from = ["monitor", "slam", "buoy", "sync", "fusion", "map"]
duration_s = 200"#;
    let cfg = run.write_config(ends, &default_graph_with_viewer(port));
    run.start_supervisor(&cfg, &[]);
    // A second client subscribes to everything and stops reading: the SDK drops for it (and
    // says so in its log, which the viewer counts), the pipeline does not wait.
    let stalled = Command::new("python3")
        .arg(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("python/foxglove_stalled_client.py"))
        .args(["--url", &format!("ws://127.0.0.1:{port}"), "--stall-s", "8"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("python3 runs the stalled client");
    let client = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("python/foxglove_ws_client.py");
    let mut cmd = Command::new("python3");
    cmd.arg(&client).args(["--url", &format!("ws://127.0.0.1:{port}"), "--timeout-s", "150", "--min-messages", "2"]);
    for topic in
        ["/slam/path", "/buoy/path", "/fused/path", "/fused/pose", "/cloud", "/landmarks", "/octree", "/processes"]
    {
        cmd.args(["--want", topic]);
    }
    // The mapper fills its map only once fused poses come (later on a loaded machine): the client
    // waits for what the assertions below read rather than stop at the first empty full sets.
    for (topic, field, n) in [
        ("/octree", "points", "100"),
        ("/cloud", "points", "1"),
        ("/landmarks", "points", "1"),
        ("/ground_truth/path", "poses", "2"),
        ("/slam/path", "poses", "2"),
        ("/buoy/path", "poses", "2"),
        ("/fused/path", "poses", "2"),
    ] {
        cmd.args(["--at-least", topic, field, n]);
    }
    let out = cmd.stderr(Stdio::piped()).output().expect("python3 runs the client");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "client: {stderr}\n{stdout}\nrun log:\n{}", run.log());
    let seen: serde_json::Value = serde_json::from_str(stdout.trim()).expect("the client's JSON");
    let t = &seen["topics"];
    // Foxglove's own schemas, decoded with what the server advertised.
    for (topic, schema) in [
        ("/slam/path", "foxglove.PosesInFrame"),
        ("/fused/pose", "foxglove.PoseInFrame"),
        ("/cloud", "foxglove.PointCloud"),
        ("/octree", "foxglove.PointCloud"),
        ("/processes", "foxglove.Log"),
    ] {
        assert_eq!(t[topic]["schema"], schema, "{topic}: {seen:#}");
    }
    for topic in ["/ground_truth/path", "/slam/path", "/buoy/path", "/fused/path"] {
        assert!(t[topic]["last"]["poses"].as_u64().unwrap_or(0) >= 2, "{topic}: {seen:#}");
        assert_eq!(t[topic]["last"]["finite"], true, "{topic}: {seen:#}");
        assert_eq!(t[topic]["last"]["frame_id"], "world", "{topic}: {seen:#}");
    }
    let cloud = &t["/cloud"]["last"];
    assert!(cloud["points"].as_u64().unwrap_or(0) >= 1, "{seen:#}");
    assert_eq!(cloud["fields"], serde_json::json!(["x", "y", "z"]), "{seen:#}");
    assert_eq!(cloud["finite"], true, "{seen:#}");
    let octree = &t["/octree"]["last"];
    assert!(octree["points"].as_u64().unwrap_or(0) >= 100, "the octree's voxels: {seen:#}");
    assert_eq!(octree["fields"][3], "occupancy", "{seen:#}");
    assert!(t["/landmarks"]["last"]["points"].as_u64().unwrap_or(0) >= 1, "{seen:#}");
    let state = t["/processes"]["last"]["message"].as_str().unwrap_or_default();
    assert!(state.contains("messages in"), "{state}");

    let stalled = stalled.wait_with_output().expect("the stalled client ends");
    assert!(stalled.status.success(), "stalled client: {}", String::from_utf8_lossy(&stalled.stderr));
    let status = run.wait_supervisor(LONG).expect("the run ends");
    assert_eq!(status.code(), Some(0), "{}", run.log());
    assert_eq!(run.leftovers(), Vec::<PathBuf>::new(), "iceoryx2 files left behind");
    let s = run.summary();
    use crate::summary_schema::part;
    let viewer: viewer_stage::summary::ViewerPart = part(&s);
    let mapper: octree_mapper_stage::summary::OctreeMapperPart = part(&s);
    let sup: supervisor::report::SupervisorPart = part(&s);
    let v = &viewer.viewer;
    assert!(v.clients_max >= 1, "{v:?}");
    assert!(v.not_shown.is_empty(), "{v:?}");
    // The viewer saw every cloud ingest sent: nothing lost to the view. The mapper, paced at 4x
    // real time without back-pressure, may miss some on a loaded machine (CI: 16 and 15 of 17
    // inserted): counted, and in summary.json's dropped list, never silent.
    let sent = part::<ingest_stage::summary::IngestPart>(&s).ingest.messages.cloud;
    assert_eq!(v.channels["/cloud"].received, sent, "{v:?}\n{:#}", s["ingest"]);
    let c = &mapper.octree_mapper.counters;
    let (inserted, missed) = (c.clouds_inserted, c.clouds_missed);
    let dropped = c.clouds_dropped_behind + c.clouds_dropped_no_pose;
    // A cloud that never reached the mapper (its queue full) is counted by the publisher as
    // undelivered to `map`, and by the mapper as missed once a later cloud shows the gap in the
    // sequence numbers: the last cloud's loss only the publisher can see (2026-12-07 in CI: 15
    // inserted, 1 missed, 1 undelivered at the end, of 17).
    let undelivered: u64 = sup
        .undelivered
        .iter()
        .filter(|u| u.publisher == "ingest" && u.service == "pipeline/sensors/cloud" && u.consumer == "map")
        .map(|u| u.messages)
        .sum();
    assert!(missed <= undelivered, "every gap the mapper saw was a failed delivery: {c:?}, {:?}", sup.undelivered);
    assert_eq!(inserted + undelivered + dropped, sent, "{c:?}, {:?}", sup.undelivered);
    // This test's mapper also sends its full voxel map every second (voxels_full_interval_s), so
    // at 4x real time it misses some of the 17 clouds on a loaded machine (CI: 1 and 2).
    assert!(inserted * 2 >= sent, "the mapper took most clouds: {c:?}");
    let listed: u64 = sup.dropped.iter().filter(|d| d.process == "map").map(|d| d.messages).sum();
    assert_eq!(listed, missed + dropped, "the mapper's losses are listed: {:#}", s["dropped"]);
    assert!(v.channels["/cloud"].logged >= 1, "{v:?}");
    // The stalled client lost messages: the SDK's reports of it were counted and warned about.
    assert!(v.sdk_outbox_full_reports >= 1, "{v:?}");
    assert!(run.log().contains("the Foxglove SDK dropped its oldest queued messages"), "{}", run.log());
    let end = mapper.octree_mapper.end_of_stream.as_ref().expect("the mapper reached its end of stream");
    assert!(end.voxel_stream.delta_messages >= 2, "{:?}", end.voxel_stream);
}
